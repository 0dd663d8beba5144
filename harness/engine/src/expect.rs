//! Per-target expectations files: known deviations, each with a written reason (like rustls' BoGo
//! `DisabledTests`). A listed case that deviates gets the listed verdict; the original stays in the report.

use std::path::Path;

use serde::Deserialize;

use crate::cases::Verdict;

/// Why an expectations file was rejected.
#[derive(Debug, thiserror::Error)]
#[error("{file}: {reason}")]
pub struct ExpectError {
    pub file: String,
    pub reason: String,
}

/// A parsed expectations file.
#[derive(Clone, Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Expectations {
    /// What the file is about (the target, its version).
    pub target: Option<String>,
    #[serde(rename = "deviation", default)]
    pub deviations: Vec<ExpectedDeviation>,
}

/// One known deviation.
#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ExpectedDeviation {
    /// A case id or a glob over case ids (`tcp/unit-id/*`).
    pub case: String,
    /// The verdict the case gets instead of FAIL/UNIMPLEMENTED/NON-STRICT.
    pub verdict: String,
    /// Why this is accepted: required, never empty.
    pub reason: String,
}

impl Expectations {
    /// Load and validate: every pattern compiles, every verdict is known, every reason is written.
    pub fn load(path: &Path) -> Result<Self, ExpectError> {
        let bad = |reason: String| ExpectError {
            file: path.display().to_string(),
            reason,
        };
        let text = std::fs::read_to_string(path).map_err(|e| bad(e.to_string()))?;
        let e: Expectations = toml::from_str(&text)
            .map_err(|e| bad(drives::profile::toml_error_message(&text, &e)))?;
        for d in &e.deviations {
            glob::Pattern::new(&d.case)
                .map_err(|err| bad(format!("case pattern `{}`: {err}", d.case)))?;
            d.verdict
                .parse::<Verdict>()
                .map_err(|err| bad(format!("case `{}`: {err}", d.case)))?;
            if d.reason.trim().is_empty() {
                return Err(bad(format!(
                    "case `{}` has no reason: every expected deviation needs one",
                    d.case
                )));
            }
        }
        Ok(e)
    }

    /// The deviation listed for `id`, if any (first match wins).
    pub fn lookup(&self, id: &str) -> Option<(Verdict, &str)> {
        self.deviations.iter().find_map(|d| {
            let pat = glob::Pattern::new(&d.case).ok()?;
            let opts = glob::MatchOptions {
                require_literal_separator: false,
                ..Default::default()
            };
            pat.matches_with(id, opts)
                .then(|| {
                    d.verdict
                        .parse::<Verdict>()
                        .ok()
                        .map(|v| (v, d.reason.as_str()))
                })
                .flatten()
        })
    }
}

/// What became of one entry of an expectations file in a run.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ExpectationUse {
    /// The entry's case pattern.
    pub case: String,
    /// The verdict it gives.
    pub verdict: String,
    /// Cases of the run whose id it matches (skipped ones included).
    pub matched: usize,
    /// Of those, the cases that ran (not SKIPPED).
    pub ran: usize,
    /// Cases whose deviation this entry excused (it was their first matching entry).
    pub deviated: usize,
}

/// How an entry of an expectations file fared: used, or one a run should report.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ExpectationState {
    /// It excused at least one deviation.
    Used,
    /// It matches no case of the run: a typo, a renamed case, or a case left out by the selection.
    Unmatched,
    /// Its cases were all SKIPPED: nothing to say about it.
    NotRun,
    /// Its cases ran and none deviated: the deviation is gone (fixed), the entry is stale.
    Stale,
}

impl ExpectationUse {
    /// How the entry fared.
    pub fn state(&self) -> ExpectationState {
        if self.matched == 0 {
            ExpectationState::Unmatched
        } else if self.ran == 0 {
            ExpectationState::NotRun
        } else if self.deviated == 0 {
            ExpectationState::Stale
        } else {
            ExpectationState::Used
        }
    }
}

/// Counts, per entry of an expectations file, the cases it matches and the deviations it excuses; memory
/// does not grow with the number of cases.
#[derive(Clone, Debug, Default)]
pub struct ExpectationTally {
    entries: Vec<(Option<glob::Pattern>, ExpectationUse)>,
}

impl ExpectationTally {
    /// Count one case's result.
    pub fn record(&mut self, result: &crate::CaseResult) {
        let opts = glob::MatchOptions {
            require_literal_separator: false,
            ..Default::default()
        };
        let mut first = true;
        for (pattern, entry) in &mut self.entries {
            if !pattern
                .as_ref()
                .is_some_and(|p| p.matches_with(&result.id, opts))
            {
                continue;
            }
            entry.matched += 1;
            if result.verdict != Verdict::Skipped {
                entry.ran += 1;
            }
            // As in `lookup`, the first matching entry is the one that excused the deviation.
            if std::mem::take(&mut first) && result.expected_deviation.is_some() {
                entry.deviated += 1;
            }
        }
    }

    /// Every entry, in file order.
    pub fn finish(self) -> Vec<ExpectationUse> {
        self.entries.into_iter().map(|(_, e)| e).collect()
    }
}

impl Expectations {
    /// A tally of this file's entries for one run.
    pub fn tally(&self) -> ExpectationTally {
        ExpectationTally {
            entries: self
                .deviations
                .iter()
                .map(|d| {
                    (
                        glob::Pattern::new(&d.case).ok(),
                        ExpectationUse {
                            case: d.case.clone(),
                            verdict: d.verdict.clone(),
                            matched: 0,
                            ran: 0,
                            deviated: 0,
                        },
                    )
                })
                .collect(),
        }
    }
}

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

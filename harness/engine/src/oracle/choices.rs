//! The choices a drive made during a run: for every freedom (and item of an optional group) the value it
//! showed, in which cases, and where it showed another value later. No source requires a drive to keep to
//! one choice, so a change of mind is a NON-STRICT finding, never a FAIL; the report lists every choice.

use std::collections::BTreeMap;

use drives::requirements::{FreedomKind, Requirements};
use serde::Serialize;

use super::freedoms::Shown;

/// How many case ids a choice keeps, at most (the rest are counted).
pub const CASES_KEPT: usize = 8;

/// One choice of the run.
#[derive(Clone, Debug, PartialEq, Eq, Serialize)]
pub struct Choice {
    /// The freedom's id.
    pub freedom: String,
    /// What within the freedom (an item of an optional group), or empty.
    pub about: String,
    /// The value the drive showed first.
    pub value: String,
    /// True when it is the reference drive's value.
    pub reference: bool,
    /// The cases that showed it (the first [`CASES_KEPT`]).
    pub cases: Vec<String>,
    /// How many cases showed it.
    pub count: usize,
    /// Other values shown later: (value, case id).
    pub changed: Vec<(String, String)>,
}

impl FromIterator<Choice> for ChoiceLog {
    fn from_iter<I: IntoIterator<Item = Choice>>(iter: I) -> Self {
        Self {
            entries: iter
                .into_iter()
                .map(|c| ((c.freedom.clone(), c.about.clone()), c))
                .collect(),
        }
    }
}

/// The choices of a run, in freedom order.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct ChoiceLog {
    entries: BTreeMap<(String, String), Choice>,
}

impl ChoiceLog {
    /// Record what a case showed; returns a finding's text when the drive departs from an earlier choice.
    /// Status-bit masks are recorded but never held to one value: how loose a comparison must be depends
    /// on the state the word shows, not on a choice.
    pub fn record(
        &mut self,
        shown: &Shown,
        case: &str,
        requirements: &Requirements,
    ) -> Option<String> {
        let key = (shown.freedom.clone(), shown.about.clone());
        let held = requirements
            .freedom(&shown.freedom)
            .is_none_or(|f| f.kind != FreedomKind::StatusBits);
        match self.entries.get_mut(&key) {
            None => {
                self.entries.insert(
                    key,
                    Choice {
                        freedom: shown.freedom.clone(),
                        about: shown.about.clone(),
                        value: shown.value.clone(),
                        reference: shown.reference,
                        cases: vec![case.to_string()],
                        count: 1,
                        changed: Vec::new(),
                    },
                );
                None
            }
            Some(c) if c.value == shown.value || !held => {
                if c.cases.last().map(String::as_str) != Some(case) {
                    c.count += 1;
                    if c.cases.len() < CASES_KEPT {
                        c.cases.push(case.to_string());
                    }
                }
                None
            }
            Some(c) => {
                let first = c.cases.first().cloned().unwrap_or_default();
                c.changed.push((shown.value.clone(), case.to_string()));
                let about = if c.about.is_empty() {
                    String::new()
                } else {
                    format!(" ({})", c.about)
                };
                Some(format!(
                    "the drive chose {} for freedom `{}`{about} here, but {} in case {first}: a drive keeps to one choice",
                    shown.value, c.freedom, c.value
                ))
            }
        }
    }

    /// True when `shown` is what the drive chose before for that freedom (and item), or the first it shows.
    pub fn agrees(&self, shown: &Shown) -> bool {
        self.entries
            .get(&(shown.freedom.clone(), shown.about.clone()))
            .is_none_or(|c| c.value == shown.value)
    }

    /// Every choice, by freedom and item.
    pub fn choices(&self) -> impl Iterator<Item = &Choice> {
        self.entries.values()
    }

    /// True when nothing was recorded.
    pub fn is_empty(&self) -> bool {
        self.entries.is_empty()
    }

    /// The choices as lines for a terminal or a snapshot: `freedom [about] = value (cases)`.
    pub fn lines(&self) -> Vec<String> {
        self.entries
            .values()
            .map(|c| {
                let about = if c.about.is_empty() {
                    String::new()
                } else {
                    format!(" [{}]", c.about)
                };
                let more = c.count.saturating_sub(c.cases.len());
                let more = if more > 0 {
                    format!(" and {more} more")
                } else {
                    String::new()
                };
                let changed = if c.changed.is_empty() {
                    String::new()
                } else {
                    let v: Vec<String> = c
                        .changed
                        .iter()
                        .map(|(v, case)| format!("{v} in {case}"))
                        .collect();
                    format!("; then {}", v.join(", "))
                };
                format!(
                    "{}{about} = {}{} ({}{more}){changed}",
                    c.freedom,
                    c.value,
                    if c.reference {
                        " (the reference's)"
                    } else {
                        ""
                    },
                    c.cases.join(", ")
                )
            })
            .collect()
    }
}

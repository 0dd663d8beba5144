//! The choices a drive made during a run: for every freedom (and item of an optional group) the value it
//! showed, in which cases, and where it showed another value later. No source requires a drive to keep to
//! one choice, so a change of mind is a NON-STRICT finding, never a FAIL; the report lists every choice.

use std::collections::BTreeMap;

use drives::requirements::{FreedomKind, Requirements};
use serde::Serialize;

use super::freedoms::Shown;

/// How many case ids a choice keeps, at most (the rest are counted).
pub const CASES_KEPT: usize = 8;

/// How many silences against an answered choice a link that loses frames may account for, per freedom: more
/// is the drive's own (noise hitting the same kind of request again and again is no noise).
pub const LOSSY_SILENCES: usize = 2;

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
    /// Cases that showed silence against this answered value on a link seen to lose frames in the run (see
    /// [`ChoiceLog::link_loses_frames`]): not held against the drive.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub silent_on_a_lossy_link: Vec<String>,
}

impl FromIterator<Choice> for ChoiceLog {
    fn from_iter<I: IntoIterator<Item = Choice>>(iter: I) -> Self {
        Self {
            entries: iter
                .into_iter()
                .map(|c| ((c.freedom.clone(), c.about.clone()), c))
                .collect(),
            lossy: false,
            undo: None,
        }
    }
}

/// The choices of a run, in freedom order.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct ChoiceLog {
    entries: BTreeMap<(String, String), Choice>,
    /// The link lost or damaged frames in this run (see [`ChoiceLog::link_loses_frames`]).
    lossy: bool,
    /// Since [`ChoiceLog::mark`]: each entry as it was before its first change (`None`: there was none).
    undo: Option<BTreeMap<(String, String), Option<Choice>>>,
}

impl ChoiceLog {
    /// The link to the drive lost or damaged frames in this run (a case FAILed as a damaged link makes it
    /// fail, and came through whole when run again): from now on a silence where the drive answered before
    /// (or an answer where it was silent) is no change of mind. A request damaged on its way gets no answer
    /// from any drive (serial line spec 2.5.1.2: a frame whose CRC does not check is discarded), so a silence
    /// on such a link is no evidence of a choice against an answer, which is: the answer is kept as the
    /// choice, and the case that was silent is listed with it (at most [`LOSSY_SILENCES`] a freedom).
    pub fn link_loses_frames(&mut self) {
        self.lossy = true;
    }

    /// From now on remember each entry as it was before its first change, for [`ChoiceLog::rewind`] (a case's
    /// attempt that may not be judged). Cheap: nothing is copied until an entry changes.
    pub fn mark(&mut self) {
        self.undo = Some(BTreeMap::new());
    }

    /// Put every entry back as it was at the last [`ChoiceLog::mark`], which stays set.
    pub fn rewind(&mut self) {
        let Some(undo) = self.undo.as_mut() else {
            return;
        };
        for (key, was) in std::mem::take(undo) {
            match was {
                Some(c) => {
                    self.entries.insert(key, c);
                }
                None => {
                    self.entries.remove(&key);
                }
            }
        }
    }

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
        if let Some(undo) = self.undo.as_mut()
            && !undo.contains_key(&key)
        {
            undo.insert(key.clone(), self.entries.get(&key).cloned());
        }
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
                        silent_on_a_lossy_link: Vec::new(),
                    },
                );
                None
            }
            Some(c)
                if self.lossy
                    && held
                    && (c.value == "silence") != (shown.value == "silence")
                    && if c.value == "silence" {
                        c.count
                    } else {
                        c.silent_on_a_lossy_link.len() + 1
                    } <= LOSSY_SILENCES =>
            {
                if c.value == "silence" {
                    // The answer is the choice; the cases that were silent are listed with it.
                    let mut silent = std::mem::take(&mut c.cases);
                    silent.truncate(CASES_KEPT);
                    c.silent_on_a_lossy_link = silent;
                    c.value = shown.value.clone();
                    c.reference = shown.reference;
                    c.cases = vec![case.to_string()];
                    c.count = 1;
                } else if c.silent_on_a_lossy_link.len() < CASES_KEPT {
                    c.silent_on_a_lossy_link.push(case.to_string());
                }
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

#[cfg(test)]
mod tests {
    use super::*;

    fn shown(value: &str) -> Shown {
        Shown {
            freedom: "rtu-length-framing".into(),
            about: String::new(),
            value: value.into(),
            reference: false,
        }
    }

    /// On a clean link a silence against an answer is a change of mind (NON-STRICT); on a link that lost
    /// frames in the run, up to [`LOSSY_SILENCES`] silences are not held against the answer, which becomes
    /// the choice, and the cases are listed; a third is the drive's own again.
    #[test]
    fn a_silence_on_a_link_that_loses_frames_is_not_held_against_an_answer() {
        let requirements = drives::corpus::Corpus::Embedded
            .requirements()
            .expect("requirements");
        let mut clean = ChoiceLog::default();
        assert_eq!(clean.record(&shown("silence"), "a", &requirements), None);
        assert!(
            clean
                .record(&shown("exception-03"), "b", &requirements)
                .is_some()
        );

        let mut lossy = ChoiceLog::default();
        lossy.link_loses_frames();
        assert_eq!(lossy.record(&shown("silence"), "a", &requirements), None);
        assert_eq!(
            lossy.record(&shown("exception-03"), "b", &requirements),
            None
        );
        let c = lossy.choices().next().expect("a choice");
        assert_eq!(
            (
                c.value.as_str(),
                c.cases.clone(),
                c.silent_on_a_lossy_link.clone()
            ),
            ("exception-03", vec!["b".to_string()], vec!["a".to_string()])
        );
        assert_eq!(lossy.record(&shown("silence"), "c", &requirements), None);
        assert!(
            lossy
                .record(&shown("silence"), "d", &requirements)
                .is_some(),
            "a third silence is the drive's"
        );
        // An answer against an answer is a change of mind on any link.
        assert!(
            lossy
                .record(&shown("exception-01"), "e", &requirements)
                .is_some()
        );
    }
}

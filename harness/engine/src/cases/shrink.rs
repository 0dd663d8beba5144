//! Shrinking a failing generated case against the live target.
//!
//! The case's proptest value tree is walked as proptest's own runner does (simplify while the candidate
//! still FAILs, complicate when it passes), with every candidate run against the target and judged by the
//! oracle. The walk is bounded in candidates run and in time ([`ShrinkLimits`]); the smallest candidate
//! that still FAILs is what the session writes to `corpus/regressions/<profile>/<name>.toml` (see
//! [`crate::cases::regressions`]), which the catalog replays as `regression/<profile>/<name>` from then on.

use std::collections::HashMap;
use std::time::{Duration, Instant};

use crate::cases::generated::Generator;
use crate::cases::{Case, Outgoing, Step};

/// Candidates run at most while shrinking one case, by default.
pub const DEFAULT_MAX_STEPS: usize = 200;
/// Time spent at most shrinking one case, by default.
pub const DEFAULT_MAX_TIME: Duration = Duration::from_secs(30);

/// Bounds of one shrink.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ShrinkLimits {
    /// Candidates run against the target, at most (the re-run of the original counts).
    pub max_steps: usize,
    /// Wall time, at most.
    pub max_time: Duration,
}

impl Default for ShrinkLimits {
    fn default() -> Self {
        Self {
            max_steps: DEFAULT_MAX_STEPS,
            max_time: DEFAULT_MAX_TIME,
        }
    }
}

/// Why a shrink ended.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ShrinkStop {
    /// Nothing simpler fails: the case is minimal for the generators.
    Minimal,
    /// The step bound was reached.
    Steps,
    /// The time bound was reached.
    Time,
}

/// What the walk needs of a candidate's run (the session's is a [`crate::observe::CaseResult`]).
pub trait Outcome {
    /// The candidate FAILs.
    fn fails(&self) -> bool;
    /// The findings of its FAIL.
    fn findings(&self) -> Vec<String>;
}

/// The result of shrinking one failing case.
#[derive(Clone, Debug)]
pub struct Shrunk {
    /// The case as generated.
    pub original: Case,
    /// The smallest candidate that still FAILs.
    pub case: Case,
    /// The findings of its FAIL.
    pub findings: Vec<String>,
    /// Candidates run against the target (the re-run of the original included).
    pub steps: usize,
    /// Simplifications that still failed and were kept.
    pub accepted: usize,
    pub elapsed: Duration,
    pub stop: ShrinkStop,
}

/// Re-run generated case `index` through `run` and, if it FAILs, shrink it. `None` when the re-run does
/// not FAIL (the failure needs the state earlier cases left behind).
pub fn shrink<R: Outcome, E>(
    generator: &Generator,
    index: u64,
    limits: &ShrinkLimits,
    mut run: impl FnMut(&Case) -> Result<R, E>,
) -> Result<Option<Shrunk>, E> {
    let started = Instant::now();
    let mut tree = generator.tree(index);
    let original = generator.build(&tree.current(), index);
    let first = run(&original)?;
    if !first.fails() {
        return Ok(None);
    }
    let mut best = (original.clone(), first.findings());
    let mut steps = 1usize;
    let mut accepted = 0usize;
    let mut stop = ShrinkStop::Minimal;
    // Candidates already judged (a tree can offer the same value twice); bounded by the step bound.
    let mut seen: HashMap<String, bool> = HashMap::new();
    // Cache hits cost no step: bound the walk itself too.
    let mut moves = 0usize;
    if tree.simplify() {
        loop {
            moves += 1;
            if steps >= limits.max_steps || moves > limits.max_steps.saturating_mul(20) {
                stop = ShrinkStop::Steps;
                break;
            }
            if started.elapsed() >= limits.max_time {
                stop = ShrinkStop::Time;
                break;
            }
            let candidate = generator.build(&tree.current(), index);
            let key = format!("{:?}", candidate.steps);
            let fails = match seen.get(&key) {
                Some(f) => *f,
                None => {
                    steps += 1;
                    let r = run(&candidate)?;
                    let f = r.fails();
                    if f {
                        best = (candidate, r.findings());
                    }
                    seen.insert(key, f);
                    f
                }
            };
            let moved = if fails {
                accepted += 1;
                tree.simplify()
            } else {
                tree.complicate()
            };
            if !moved {
                break;
            }
        }
    }
    Ok(Some(Shrunk {
        original,
        case: best.0,
        findings: best.1,
        steps,
        accepted,
        elapsed: started.elapsed(),
        stop,
    }))
}

/// The size of a case, for the shrink bound: (exchange steps, largest PDU in bytes).
pub fn case_size(case: &Case) -> (usize, usize) {
    let mut exchanges = 0;
    let mut largest = 0;
    for s in &case.steps {
        if let Step::Exchange { send, .. } = s {
            exchanges += 1;
            let n = match send {
                Outgoing::Pdu(p) | Outgoing::PduToUnit { pdu: p, .. } => p.len(),
                Outgoing::Mutated { pdu, mutation } => {
                    mutation.apply_to_pdu(pdu).map_or(pdu.len(), |p| p.len())
                }
                Outgoing::Batch(ps) => ps.iter().map(Vec::len).sum(),
                Outgoing::Restore { .. } | Outgoing::RestoreRead { .. } => 0,
            };
            largest = largest.max(n);
        }
    }
    (exchanges, largest)
}

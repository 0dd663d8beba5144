//! Property-generated cases. A case is described by a [`Spec`] (`spec.rs`): a short sequence of requests of
//! every function code the profile supports, drawn from its map, at its boundaries, and altered on purpose.
//! The proptest strategies (`strategy.rs`) draw descriptions, [`Spec::build`] (`build.rs`) turns one into a
//! [`Case`] for a profile, and the [`Generator`] here draws the cases of a run.
//!
//! Case `index` of seed `seed` is drawn from its own random stream, so it is the same whatever the number of
//! cases, and replays from (seed, index) alone. Ids are `gen/<seed>/<index>/<kind>`.
//!
//! Reproducibility holds for one harness version (the proptest version is pinned by Cargo.lock): the same
//! seed, profile and unit give the same cases on every transport; transport-specific alterations carry
//! `tcponly`/`rtuonly` tags and are SKIPPED on the other framing.

use proptest::strategy::{BoxedStrategy, Strategy, ValueTree};
use proptest::test_runner::{Config, RngAlgorithm, TestRng, TestRunner};

use crate::cases::Case;
use drives::profile::Profile;

mod build;
mod spec;
mod strategy;

#[cfg(feature = "arbitrary")]
pub use build::case_from_bytes;
pub use build::{GenContext, pdu_tags};
pub use spec::{
    Alter, Edge, MAX_BATCH_EXTRA, MAX_EXTEND, MAX_OPS, MAX_SPLIT_GAP_US, Op, Quantity, Req, Spec,
    Value,
};

/// The first segment of every generated case id.
pub const ID_PREFIX: &str = "gen";

/// A seed from the clock, for runs that name none (printed so that the run can be replayed).
pub fn clock_seed() -> u64 {
    let now = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .unwrap_or_default();
    // Nanoseconds mixed, then kept to 48 bits so the seed stays short to type.
    splitmix(now.as_nanos() as u64 ^ u64::from(std::process::id())) & 0xFFFF_FFFF_FFFF
}

fn splitmix(mut x: u64) -> u64 {
    x = x.wrapping_add(0x9E37_79B9_7F4A_7C15);
    let mut z = x;
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// The 32-byte ChaCha seed of case `index` of run seed `seed`.
pub fn case_rng_seed(seed: u64, index: u64) -> [u8; 32] {
    let mut out = [0u8; 32];
    let mut x = splitmix(seed) ^ index.wrapping_mul(0xD1B5_4A32_D192_ED03);
    for chunk in out.chunks_mut(8) {
        x = splitmix(x);
        chunk.copy_from_slice(&x.to_le_bytes());
    }
    out
}

/// `gen/<seed>/<index>`: the id of a generated case without its kind.
pub fn id_prefix(seed: u64, index: u64) -> String {
    format!("{ID_PREFIX}/{seed}/{index}")
}

/// (seed, index) of a generated case id.
pub fn parse_id(id: &str) -> Option<(u64, u64)> {
    let mut parts = id.split('/');
    if parts.next()? != ID_PREFIX {
        return None;
    }
    let seed = parts.next()?.parse().ok()?;
    let index = parts.next()?.parse().ok()?;
    Some((seed, index))
}

/// Draws the generated cases of one run.
pub struct Generator {
    cx: GenContext,
    strategy: BoxedStrategy<Spec>,
    seed: u64,
}

impl Generator {
    /// The generator for a profile, requests to `unit`, and a run seed.
    pub fn new(profile: &Profile, unit: u8, seed: u64) -> Self {
        let cx = GenContext::new(profile, unit);
        let strategy = cx.spec_strategy();
        Self { cx, strategy, seed }
    }

    /// The same generator with the frames for another unit sent to `foreign`, an address no device on the
    /// line answers, where it is set ([`GenContext::on_line`]).
    pub fn on_line(mut self, foreign: Option<u8>) -> Self {
        self.cx = self.cx.on_line(foreign);
        self
    }

    /// The run seed.
    pub fn seed(&self) -> u64 {
        self.seed
    }

    /// The profile data the cases are drawn from.
    pub fn context(&self) -> &GenContext {
        &self.cx
    }

    /// The value tree of case `index`: its current value is the case as generated; `simplify` and
    /// `complicate` walk toward simpler cases (the shrinker drives it).
    pub fn tree(&self, index: u64) -> Box<dyn ValueTree<Value = Spec>> {
        let rng = TestRng::from_seed(RngAlgorithm::ChaCha, &case_rng_seed(self.seed, index));
        // No failure persistence, no environment: the stream is the seed's alone.
        let config = Config {
            failure_persistence: None,
            ..Config::default()
        };
        let mut runner = TestRunner::new_with_rng(config, rng);
        // Without filters a strategy never rejects; a rejection would be a bug in the generators.
        match self.strategy.new_tree(&mut runner) {
            Ok(t) => Box::new(t),
            Err(reason) => panic!("generated case {index}: the strategy rejected: {reason}"),
        }
    }

    /// The case a spec builds under the id of case `index`.
    pub fn build(&self, spec: &Spec, index: u64) -> Case {
        spec.build(&self.cx, &id_prefix(self.seed, index))
    }

    /// Case `index`, as generated.
    pub fn case(&self, index: u64) -> Case {
        self.build(&self.tree(index).current(), index)
    }

    /// Cases `0..n`, one at a time (nothing is kept).
    pub fn cases(&self, n: u64) -> impl Iterator<Item = Case> + '_ {
        (0..n).map(|i| self.case(i))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ids_round_trip() {
        assert_eq!(parse_id(&format!("{}/x", id_prefix(42, 7))), Some((42, 7)));
        assert_eq!(parse_id("golden/x/y"), None);
    }

    #[test]
    fn case_streams_differ_by_index_and_seed() {
        assert_ne!(case_rng_seed(1, 0), case_rng_seed(1, 1));
        assert_ne!(case_rng_seed(1, 0), case_rng_seed(2, 0));
        assert_eq!(case_rng_seed(5, 9), case_rng_seed(5, 9));
    }
}

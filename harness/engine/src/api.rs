//! The library API: run the conformance catalog against a drive that lives in your own process, from a
//! `cargo test` in your firmware repository.
//!
//! 1. Implement [`Device`] for your firmware's request handler (request PDU in, response PDU out).
//! 2. Build a [`Session`]: the profile that describes your drive (a corpus name, a profile file, or a
//!    [`Profile`]), your device, optionally the cases to run ([`SessionBuilder::cases`]).
//! 3. [`SessionBuilder::run`] runs the cases on a virtual clock (no sockets, no waiting) and gives
//!    [`Results`] to assert on: [`Results::assert_passes`] panics with every FAIL and its findings.
//!
//! The harness frames the PDUs as Modbus/TCP or RTU ([`DeviceTarget`]), and judges every answer against
//! the reference drive of the profile, as `modbus-harness run` does: the same catalog (golden frames of a
//! corpus profile, spec, transport and profile cases, the regressions), the same freedoms. Unlike `run`:
//! every case runs (no safety policy: nothing in process can move a motor), the device is not left as
//! found (it is yours to drop), and no report files, expectations file, snapshots or generated cases
//! (use the command line for those). `examples/toy-firmware/` in the repository is a complete example to
//! copy.
//!
//! ```
//! use modbus_harness_engine::api::{Device, Profile, Session, Verdict};
//!
//! /// A drive with 8 holding registers (FC 03 and 06 only); everything else: exception 01.
//! struct Tiny {
//!     regs: [u16; 8],
//! }
//!
//! impl Device for Tiny {
//!     fn handle(&mut self, _unit: u8, pdu: &[u8]) -> Option<Vec<u8>> {
//!         let fc = *pdu.first()?;
//!         let word = |i: usize| u16::from_be_bytes([pdu[i], pdu[i + 1]]);
//!         let exception = |code: u8| Some(vec![fc | 0x80, code]);
//!         match fc {
//!             0x03 if pdu.len() == 5 => {
//!                 let (addr, n) = (word(1) as usize, word(3) as usize);
//!                 if !(1..=125).contains(&n) {
//!                     return exception(0x03);
//!                 }
//!                 let Some(regs) = self.regs.get(addr..addr + n) else {
//!                     return exception(0x02);
//!                 };
//!                 let mut out = vec![0x03, 2 * n as u8];
//!                 regs.iter().for_each(|r| out.extend(r.to_be_bytes()));
//!                 Some(out)
//!             }
//!             0x06 if pdu.len() == 5 => match self.regs.get_mut(word(1) as usize) {
//!                 Some(r) => {
//!                     *r = word(3);
//!                     Some(pdu.to_vec())
//!                 }
//!                 None => exception(0x02),
//!             },
//!             0x03 | 0x06 => exception(0x03),
//!             _ => exception(0x01),
//!         }
//!     }
//! }
//!
//! let profile = r#"
//! [device]
//! id = "tiny"
//! name = "Tiny drive"
//! vendor = "Example"
//! transports = ["tcp"]
//! word_order = "high-first"
//! default_unit = 1
//! unit_ids = [0, 255]
//! max_pdu = 253
//!
//! [[register]]
//! address = 0
//! count = 8
//! width = 1
//! name = "R{address}"
//! access = "rw"
//! table = "holding"
//!
//! [[function]]
//! code = 0x03
//! name = "Read Holding Registers"
//!
//! [[function]]
//! code = 0x06
//! name = "Write Single Register"
//! "#;
//! let results = Session::builder()
//!     .profile(Profile::parse("tiny", profile).unwrap())
//!     .device(Tiny { regs: [0; 8] })
//!     .cases("spec/*")
//!     .run();
//! results.assert_passes();
//! assert!(results.count(Verdict::Pass) > 0);
//! ```

use std::collections::BTreeMap;
use std::fmt;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use crate::expect::Expectations;
use crate::runner::Runner;
use crate::session::{self, Options, SessionError};
use crate::targets::TargetUrl;
use crate::targets::sim::SimTarget;
use codec::Framing;
use drives::corpus::Corpus;

pub use crate::cases::Verdict;
pub use crate::observe::{CaseResult, StepResult};
pub use crate::targets::device::{Device, DeviceTarget};
pub use drives::profile::Profile;

/// The profile a session judges the device by: a corpus name (`"mdrive"`, `"generic"`), a profile file,
/// or a [`Profile`] already loaded. `&str` and `String` are a file when they contain a `/` or end in
/// `.toml` (as `--profile` on the command line), else a name.
#[derive(Clone, Debug)]
pub enum ProfileSource {
    /// A profile of the corpus by name, or a file by path (see above).
    Named(String),
    /// A profile file.
    File(PathBuf),
    /// A profile in memory.
    Profile(Box<Profile>),
}

impl From<&str> for ProfileSource {
    fn from(s: &str) -> Self {
        ProfileSource::Named(s.to_string())
    }
}

impl From<String> for ProfileSource {
    fn from(s: String) -> Self {
        ProfileSource::Named(s)
    }
}

impl From<&Path> for ProfileSource {
    fn from(p: &Path) -> Self {
        ProfileSource::File(p.to_path_buf())
    }
}

impl From<PathBuf> for ProfileSource {
    fn from(p: PathBuf) -> Self {
        ProfileSource::File(p)
    }
}

impl From<Profile> for ProfileSource {
    fn from(p: Profile) -> Self {
        ProfileSource::Profile(Box::new(p))
    }
}

/// A conformance run against an in-process [`Device`]; start with [`Session::builder`].
pub struct Session;

impl Session {
    /// A builder with no profile and no device yet; both are required.
    pub fn builder() -> SessionBuilder {
        SessionBuilder {
            profile: None,
            device: None,
            include: Vec::new(),
            exclude: Vec::new(),
            framing: None,
            unit: None,
            corpus: Corpus::Embedded,
        }
    }
}

/// Why a session could not run (a test usually lets [`SessionBuilder::run`] panic with it instead).
#[derive(Debug, thiserror::Error)]
pub enum ApiError {
    /// [`SessionBuilder::profile`] was not called.
    #[error("no profile: call .profile(\"generic\" | \"path/to/profile.toml\" | Profile)")]
    NoProfile,
    /// [`SessionBuilder::device`] was not called.
    #[error("no device: call .device(your Device)")]
    NoDevice,
    /// The selection matched no case of the catalog: a test that runs nothing proves nothing.
    #[error("no case matches the selection (include {include:?}, exclude {exclude:?})")]
    NoCases {
        include: Vec<String>,
        exclude: Vec<String>,
    },
    /// A glob of [`SessionBuilder::cases`] or [`SessionBuilder::exclude`] is not a valid pattern.
    #[error("`{pattern}` is not a valid glob: {reason}")]
    BadGlob { pattern: String, reason: String },
    /// The profile could not be loaded, or the run failed.
    #[error(transparent)]
    Session(#[from] SessionError),
}

/// What a session runs: set with the methods below, then [`run`](Self::run).
pub struct SessionBuilder {
    profile: Option<ProfileSource>,
    device: Option<Box<dyn Device>>,
    include: Vec<String>,
    exclude: Vec<String>,
    framing: Option<Framing>,
    unit: Option<u8>,
    corpus: Corpus,
}

impl SessionBuilder {
    /// The profile the device is judged by (required): `"generic"`, `"mdrive"`, `"./drive.toml"`, a
    /// `Path`, or a [`Profile`].
    pub fn profile(mut self, profile: impl Into<ProfileSource>) -> Self {
        self.profile = Some(profile.into());
        self
    }

    /// The device under test (required).
    pub fn device(mut self, device: impl Device + 'static) -> Self {
        self.device = Some(Box::new(device));
        self
    }

    /// Run only the cases whose id matches this glob (`"spec/*"`, `"tcp/*"`, an exact id, or an id prefix
    /// such as `"spec/6.3"`); repeatable, a case matching any of them runs. Default: every case.
    pub fn cases(mut self, glob: &str) -> Self {
        self.include.push(glob.to_string());
        self
    }

    /// Leave out the cases whose id matches this glob (repeatable).
    pub fn exclude(mut self, glob: &str) -> Self {
        self.exclude.push(glob.to_string());
        self
    }

    /// Frame the PDUs as Modbus/TCP (the default when the profile lists the `tcp` transport).
    pub fn tcp(mut self) -> Self {
        self.framing = Some(Framing::Tcp);
        self
    }

    /// Frame the PDUs as RTU, 19200 baud 8E1 on a virtual line (the default for an RTU-only profile).
    pub fn rtu(mut self) -> Self {
        self.framing = Some(Framing::Rtu);
        self
    }

    /// The unit id / slave address the cases address (default: the profile's `default_unit`).
    pub fn unit(mut self, unit: u8) -> Self {
        self.unit = Some(unit);
        self
    }

    /// Load named profiles, golden frames and regressions from a directory laid out like `corpus/`
    /// instead of the corpus built into the harness.
    pub fn corpus_dir(mut self, dir: impl Into<PathBuf>) -> Self {
        self.corpus = Corpus::Dir(dir.into());
        self
    }

    /// Run the selected cases and return the results; panics when the run cannot be made (no profile or
    /// device, a profile that does not load, a selection that matches nothing), with the reason.
    #[track_caller]
    pub fn run(self) -> Results {
        match self.try_run() {
            Ok(r) => r,
            Err(e) => panic!("modbus-harness session could not run: {e}"),
        }
    }

    /// Run the selected cases; an error says why the run could not be made.
    pub fn try_run(self) -> Result<Results, ApiError> {
        let started = Instant::now();
        let device = self.device.ok_or(ApiError::NoDevice)?;
        let profile = match self.profile.ok_or(ApiError::NoProfile)? {
            ProfileSource::Named(n) => self.corpus.load(&n).map_err(SessionError::from)?,
            ProfileSource::File(p) => Profile::load(&p)
                .map_err(|e| SessionError::from(drives::corpus::CorpusError::from(e)))?,
            ProfileSource::Profile(p) => *p,
        };
        for pattern in self.include.iter().chain(&self.exclude) {
            glob::Pattern::new(pattern).map_err(|e| ApiError::BadGlob {
                pattern: pattern.clone(),
                reason: e.to_string(),
            })?;
        }
        let framing = self.framing.unwrap_or(if profile.speaks_tcp() {
            Framing::Tcp
        } else {
            Framing::Rtu
        });
        // The session's own planning, as for an in-process simulator of this profile: every case runs
        // (no safety policy: nothing here can move a motor), framed as asked.
        let mut opts = Options::new(TargetUrl::Sim {
            profile: profile.device.id.clone(),
            rtu: Some(framing == Framing::Rtu),
        });
        opts.corpus = self.corpus;
        opts.unit = self.unit;
        opts.include = self.include;
        opts.exclude = self.exclude;
        let planned = session::plan(&opts, &profile)?;
        if planned.is_empty() {
            return Err(ApiError::NoCases {
                include: opts.include,
                exclude: opts.exclude,
            });
        }
        let cfg = session::config(&opts, &profile);
        let target = DeviceTarget::new(device, framing);
        let shadow =
            SimTarget::reference(&profile, cfg.unit, drives::Choices::reference(), &target);
        let mut runner = Runner::new(
            Box::new(target),
            shadow,
            profile.clone(),
            cfg,
            Expectations::default(),
        )
        .with_requirements(session::requirements_of(&opts.corpus)?);
        runner.learn_word_order();
        runner.learn_fc43_form();
        runner.learn_input_addressing();
        let mut cases = Vec::with_capacity(planned.len());
        for (case, skip) in planned {
            let result = match skip {
                Some(reason) => CaseResult::skipped(&case.id, reason),
                None => runner
                    .run_case(&case)
                    .map_err(|e| ApiError::Session(e.into()))?,
            };
            cases.push(result);
        }
        Ok(Results {
            profile: profile.device.id.clone(),
            framing,
            cases,
            duration: started.elapsed(),
        })
    }
}

/// The verdicts of a session, to assert on. `Display` prints the counts and every FAIL with its findings.
#[derive(Debug)]
pub struct Results {
    profile: String,
    framing: Framing,
    cases: Vec<CaseResult>,
    duration: Duration,
}

impl Results {
    /// Every case that ran or was skipped, in run order, with its steps, findings and bytes.
    pub fn cases(&self) -> &[CaseResult] {
        &self.cases
    }

    /// The result of the case `id`, if it was selected.
    pub fn case(&self, id: &str) -> Option<&CaseResult> {
        self.cases.iter().find(|c| c.id == id)
    }

    /// The verdict of the case `id`, if it was selected.
    pub fn verdict(&self, id: &str) -> Option<Verdict> {
        self.case(id).map(|c| c.verdict)
    }

    /// The number of cases with verdict `v`.
    pub fn count(&self, v: Verdict) -> usize {
        self.cases.iter().filter(|c| c.verdict == v).count()
    }

    /// The number of cases per verdict (verdicts no case had are left out).
    pub fn counts(&self) -> BTreeMap<Verdict, usize> {
        let mut m = BTreeMap::new();
        for c in &self.cases {
            *m.entry(c.verdict).or_insert(0) += 1;
        }
        m
    }

    /// The FAIL cases, in run order.
    pub fn failures(&self) -> impl Iterator<Item = &CaseResult> {
        self.cases.iter().filter(|c| c.verdict == Verdict::Fail)
    }

    /// The ids of the FAIL cases, in run order.
    pub fn failing_ids(&self) -> Vec<&str> {
        self.failures().map(|c| c.id.as_str()).collect()
    }

    /// True when no case FAILed (what `modbus-harness run` exits 0 on).
    pub fn passed(&self) -> bool {
        self.failures().next().is_none()
    }

    /// The wall time of the run.
    pub fn duration(&self) -> Duration {
        self.duration
    }

    /// Panic unless no case FAILed and at least one case ran; the message lists every FAIL with its
    /// findings (the first 50).
    #[track_caller]
    pub fn assert_passes(&self) {
        let ran = self.cases.len() - self.count(Verdict::Skipped);
        if ran == 0 {
            panic!("no case ran (all {} skipped)", self.cases.len());
        }
        if !self.passed() {
            panic!("{self}");
        }
    }

    /// Panic unless the case `id` ran and FAILed: for a test that shows a known bug is caught. The message
    /// says what the case gave instead.
    #[track_caller]
    pub fn assert_fails(&self, id: &str) {
        match self.case(id) {
            Some(c) if c.verdict == Verdict::Fail => {}
            Some(c) => panic!(
                "expected {id} to FAIL, it was {}{}\n{self}",
                c.verdict,
                c.reason
                    .as_ref()
                    .map(|r| format!(" ({r})"))
                    .unwrap_or_default()
            ),
            None => panic!("expected {id} to FAIL, but no such case was selected\n{self}"),
        }
    }
}

impl fmt::Display for Results {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let counts = self
            .counts()
            .into_iter()
            .map(|(v, n)| format!("{n} {v}"))
            .collect::<Vec<_>>()
            .join(", ");
        let framing = if self.framing == Framing::Rtu {
            "RTU"
        } else {
            "Modbus/TCP"
        };
        writeln!(
            f,
            "modbus-harness: {} case(s) against profile `{}` over {framing} in {:.2?}: {counts}",
            self.cases.len(),
            self.profile,
            self.duration
        )?;
        let failures: Vec<&CaseResult> = self.failures().collect();
        for c in failures.iter().take(50) {
            writeln!(f, "FAIL {}", c.id)?;
            for finding in c.findings() {
                writeln!(f, "    {finding}")?;
            }
            if let Some(r) = &c.reason {
                writeln!(f, "    ({r})")?;
            }
        }
        if failures.len() > 50 {
            writeln!(f, "... and {} more FAIL(s)", failures.len() - 50)?;
        }
        Ok(())
    }
}

//! The freedom space (issue 12, item 4): the reference drives, taking the admissible values of the freedoms
//! they can simulate (each value alone, then seeded random combinations of all of them), pass the whole
//! catalog, because the oracle judges by the requirements and not by the reference drive's choices; every
//! value is shown to reach the wire (the run's "choices this drive made" records it) or is listed here as
//! one the catalog never meets; and every fault of the fault matrix still FAILs its witness case in every
//! such configuration, so admitting other answers did not blind a check.
//!
//! The Modbus/TCP transport freedoms (unit ids, pipelined answer order and Server Busy, MBAP lengths that
//! disagree with the PDU, PDUs over 253 bytes), the answer to a truncated PDU, the exception check order,
//! the FC 08 counters, the FC 11/0B fields, a half register write accepted, the vendor field readings and
//! the SD2x status bits and watchdog and the SD2x FC 43 form without the layout's reserved byte are part of
//! it. The one value left out is `close` on a profile without Modbus/TCP (`drives::choices::simulated_on`:
//! no connection to close).

use std::collections::BTreeSet;
use std::sync::Mutex;

use drives::choices::simulated_on;
use drives::corpus::Corpus;
use drives::requirements::{Freedom, FreedomValue};
use drives::{Fault, FaultSet};
use engine::Verdict;
use engine::session::{Options, RunOutcome};
use engine::targets::TargetUrl;
use test_support::{failures_of, run_quietly};

use super::fault_matrix::WITNESSES;

const PROFILES: &[&str] = &["generic", "mdrive", "lmd", "sd2x"];

/// Random combinations per profile, and their seed.
const COMBINATIONS: usize = 3;
const SEED: u64 = 0x5EED_F4EE_D000_u64;

/// Values the catalog never meets on a profile: no case sends what the freedom is about, because no case
/// may do so safely on a real drive by default. They stay simulated and admitted. (profile, "freedom=value")
const NOT_EXERCISED: &[(&str, &str)] = &[
    // The generic profile declares every public function the freedom is about.
    ("generic", "served-extra-function=served"),
    // Reading an instruction register (MA, MR, SL, ...) the profile takes as write-only: no case reads
    // one (a drive that took the read for the instruction could move).
    ("lmd", "lmd-inferred-write-only=rw"),
    ("mdrive", "mdrive-inferred-write-only=rw"),
    // Nor is a refusal of such a read, whatever its code.
    ("mdrive", "read-write-only-exception=4"),
    ("lmd", "read-write-only-exception=4"),
    // The MDrive has no read-only mnemonic, and every write-only one is a program command or a move
    // (flagged destructive or motion: its manual prints FC 0x41 for them, so a read may act).
    ("mdrive", "mnemonic-access-exception=1"),
    ("mdrive", "mnemonic-access-exception=3"),
    ("mdrive", "mnemonic-access-exception=4"),
    // The catalog writes no value outside a register's `safe_values` (generated cases may): nothing shows
    // a drive refusing one; generic and the SD2x have no such register. The MDrive's and LMD's DC and IC
    // (`operand_open`: a drive may refuse any value) are written, and a drive taking this choice refuses them
    // (its catalog PASSes here), but a 03 to a write of an instruction the profile infers write-only has a
    // second reason (`*-inferred-write-only`: a drive taking it as writable refuses by value), so the run
    // records no choice from it (`freedoms::unambiguous`).
    ("generic", "value-meaning-open=exception-03"),
    ("mdrive", "value-meaning-open=exception-03"),
    ("lmd", "value-meaning-open=exception-03"),
    ("sd2x", "value-meaning-open=exception-03"),
    ("generic", "value-meaning-open=exception-04"),
    ("mdrive", "value-meaning-open=exception-04"),
    ("lmd", "value-meaning-open=exception-04"),
    ("sd2x", "value-meaning-open=exception-04"),
    // A drive busy after an NVM save: the runner sends a request answered Server Busy (06) again until
    // the drive is free (App 7), so no verdict records the choice; the catalog with it PASSes here, and
    // without the retransmission it FAILs (runner tests `a_request_answered_server_busy_is_sent_again_*`).
    // Only a request of a batch, which is not sent again, shows it (no catalog case sends one behind a
    // save: runner test `a_batched_request_refused_busy_after_a_save_is_busy_with_the_save`).
    ("mdrive", "busy-after-long-command=all-requests"),
    ("mdrive", "busy-after-long-command=writes"),
    ("lmd", "busy-after-long-command=all-requests"),
    ("lmd", "busy-after-long-command=writes"),
    // No catalog case sends an FC 43 to another node-ID, nor an FC 08 of an unlisted sub-function with a
    // data field of another size (generated cases do: `generated_cases_admit_the_vendor_readings_*`).
    ("sd2x", "sd2x-fc43-node-id=3"),
    ("sd2x", "sd2x-diagnostic-check-order=1"),
    // The SD2x's map has no 49 readable registers end to end (its limit is 48): no case shows a drive that
    // serves more than its manual's limit.
    ("sd2x", "quantity-over-device-limit-served=response"),
    // An RTU frame has no length field: the catalog's case of a request longer than its layout runs on
    // Modbus/TCP only (a slave framing by the layout reads the extra byte and the CRC as a frame in error).
    ("sd2x", "trailing-bytes=silence"),
    ("sd2x", "trailing-bytes=response"),
    // The SD2x's writable registers are motion registers and the watchdog: no half of one is written.
    ("sd2x", "partial-register-write=exception-03"),
    ("sd2x", "partial-register-write=exception-04"),
    ("sd2x", "partial-register-write=response"),
    // Profiles without FC 11 (Report Server ID) or FC 0B (Get Comm Event Counter): nothing shows the choice.
    ("mdrive", "run-indicator-status=off"),
    ("lmd", "run-indicator-status=off"),
    ("sd2x", "run-indicator-status=off"),
    ("mdrive", "event-counter-clear-counted=counted"),
    ("lmd", "event-counter-clear-counted=counted"),
    ("sd2x", "event-counter-clear-counted=counted"),
    // On the counter case's sequence (clear, a read, a bad CRC, a frame for another slave, an exception,
    // the counter reads) the responses sent before the 0x0E read, the clear's own included, are as many as
    // the slave messages counting that read: both readings give the same number.
    (
        "sd2x",
        "diagnostic-counter-semantics=slave-count-is-responses-sent",
    ),
    // sim:sd2x speaks RTU, the SD2x's only transport: the unit ids of Modbus/TCP and the answers of a
    // gateway in front of it show over Modbus/TCP only (tests/engine/gateway.rs shows each of them on
    // sim:sd2x?transport=tcp).
    ("sd2x", "tcp-unit-ids=silence"),
    ("sd2x", "tcp-unit-ids=exception-0B"),
    ("sd2x", "tcp-unit-ids=exception-0A"),
    ("sd2x", "gateway-no-response=exception-0B"),
    ("sd2x", "gateway-no-response=exception-0A"),
    // A serial line's frame not as long as its function's rules make it: sim:generic, sim:mdrive and sim:lmd
    // speak Modbus/TCP, whose MBAP length gives the frame (sim:sd2x shows it, and the RTU transports of the
    // others in `run_transports`).
    ("generic", "rtu-length-framing=silence"),
    ("mdrive", "rtu-length-framing=silence"),
    ("lmd", "rtu-length-framing=silence"),
];

/// More cases that see a fault where a choice makes its witness a refusal: (fault, target, cases).
const ALSO_WITNESSED: &[(&str, &str, &[&str])] = &[(
    "vendor-write-not-applied",
    "sim:lmd",
    &["profile/lmd/mnemonic/mu/write"],
)];

/// Faults no catalog case can see on a drive that takes all of these choices (a `FREEDOM=` prefix each):
/// (fault, choices). An LMD refusing S1-S4 (`lmd-mnemonics-from-mdrive-examples`) and MU
/// (`lmd-closed-loop-only`) has no FC 0x42 setting left whose manual example differs from the reference's
/// power-up value (its default, else its example), so a write it does not store reads back the same. On a
/// real drive whose values are not the examples, the other setting cases see it.
const BLIND_TOGETHER: &[(&str, &[&str])] = &[(
    "vendor-write-not-applied",
    &[
        "lmd-mnemonics-from-mdrive-examples=",
        "lmd-closed-loop-only=",
    ],
)];

/// Witnesses whose exception a drive's choice replaces with silence or a close, so that a fault changing the
/// exception has nothing to change there: (fault, case, a `FREEDOM=` prefix). The fault's other witnesses
/// still FAIL under the choice.
const NO_EXCEPTION_TO_CHANGE: &[(&str, &str, &str)] = &[(
    "wrong-exception-code",
    "spec/app-4.1/request-fc-zero/fc-0x00",
    "request-fc-zero=",
)];

/// Witnesses a drive's choice makes inapplicable (SKIPPED by the runner, with the reason): (choice, case).
/// A drive that takes FC 43 in the manual's example form has no Reserved field to set.
const INAPPLICABLE: &[(&str, &str)] = &[(
    "sd2x-fc43-reserved-byte=without-reserved-byte",
    "profile/sd2x/object/reserved-nonzero/read",
)];

fn label(f: &Freedom, v: &FreedomValue) -> String {
    format!("{}={v}", f.id)
}

/// The simulated non-reference values of the freedoms of `profile`.
fn space(profile: &str) -> Vec<(Freedom, Vec<FreedomValue>)> {
    let requirements = Corpus::Embedded.requirements().expect("requirements");
    let device = Corpus::Embedded.profile(profile).expect("profile");
    requirements
        .freedoms_for(profile)
        .map(|f| {
            let values: Vec<FreedomValue> = f
                .values
                .iter()
                .skip(1)
                .filter(|v| simulated_on(f, v, &device))
                .cloned()
                .collect();
            (f.clone(), values)
        })
        .filter(|(_, v)| !v.is_empty())
        .collect()
}

fn options(target: &str, choose: &[String]) -> Options {
    let mut o = Options::new(TargetUrl::parse(target).expect("url"));
    o.choose = choose.to_vec();
    o
}

fn run(target: &str, choose: &[String]) -> RunOutcome {
    run_quietly(&options(target, choose))
        .unwrap_or_else(|e| panic!("{target} --choose {choose:?}: {e}"))
}

/// True when the run recorded the drive choosing `value` for `freedom` (in some case).
fn exercised(out: &RunOutcome, freedom: &str, value: &FreedomValue) -> bool {
    out.summary.choices.iter().any(|c| {
        c.freedom == freedom
            && (c.value == value.to_string()
                || c.changed.iter().any(|(v, _)| *v == value.to_string()))
    })
}

/// xorshift64*: a reproducible choice of values without a dependency.
struct Rng(u64);

impl Rng {
    fn below(&mut self, n: usize) -> usize {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        (self.0.wrapping_mul(0x2545_F491_4F6C_DD1D) >> 33) as usize % n
    }
}

/// Every configuration of the space: (profile, choices), each value alone, then the combinations.
fn configurations() -> Vec<(&'static str, Vec<String>)> {
    let mut out = Vec::new();
    let mut rng = Rng(SEED);
    for &p in PROFILES {
        let space = space(p);
        for (f, values) in &space {
            for v in values {
                out.push((p, vec![label(f, v)]));
            }
        }
        for _ in 0..COMBINATIONS {
            // Each freedom at a random one of all its simulated values, the reference's included.
            let combo: Vec<String> = space
                .iter()
                .filter_map(|(f, values)| {
                    let i = rng.below(values.len() + 1);
                    values.get(i).map(|v| label(f, v))
                })
                .collect();
            if !combo.is_empty() {
                out.push((p, combo));
            }
        }
    }
    out
}

/// Run `jobs` on two threads (the CI machine has two cores), collecting what each returns.
fn on_two_threads<T: Send, R: Send>(jobs: Vec<T>, work: impl Fn(T) -> R + Sync) -> Vec<R> {
    let queue = Mutex::new(jobs);
    let results = Mutex::new(Vec::new());
    std::thread::scope(|s| {
        for _ in 0..2 {
            s.spawn(|| {
                loop {
                    let Some(job) = queue.lock().expect("queue").pop() else {
                        break;
                    };
                    let r = work(job);
                    results.lock().expect("results").push(r);
                }
            });
        }
    });
    results.into_inner().expect("results")
}

/// Run `work` on every job on two threads ([`on_two_threads`]); panics listing every problem it reported.
fn assert_no_problems<T: Send, P: IntoIterator<Item = String> + Send>(
    jobs: Vec<T>,
    work: impl Fn(T) -> P + Sync,
) {
    let problems: Vec<String> = on_two_threads(jobs, work).into_iter().flatten().collect();
    assert!(problems.is_empty(), "{problems:#?}");
}

#[test]
fn drives_taking_any_admissible_choice_pass_the_catalog_and_faults_still_fail_their_witnesses() {
    let configs = configurations();
    assert!(
        configs.len() > 40,
        "the space shrank to {} configurations",
        configs.len()
    );
    let results = on_two_threads(configs, |(profile, choose)| {
        let target = format!("sim:{profile}");
        let out = run(&target, &choose);
        let mut problems = Vec::new();
        if out.summary.count(Verdict::Fail) > 0 {
            problems.push(format!(
                "{target} --choose {}: {} FAIL: {:#?}",
                choose.join(" "),
                out.summary.count(Verdict::Fail),
                failures_of(&out)
            ));
        }
        let mut unexercised = Vec::new();
        if let [one] = choose.as_slice() {
            let (id, value) = one.split_once('=').expect("label");
            let requirements = Corpus::Embedded.requirements().expect("requirements");
            let f = requirements.freedom(id).expect("freedom");
            let v = f
                .values
                .iter()
                .find(|v| v.to_string() == value)
                .expect("value");
            if !exercised(&out, id, v) {
                unexercised.push((profile, one.clone()));
            }
        }
        // Every witness of this profile still FAILs with its fault under these choices.
        for (fault, witness_target, case) in WITNESSES {
            if witness_target
                .strip_prefix("sim:")
                .map(|t| t.split('?').next())
                != Some(Some(profile))
            {
                continue;
            }
            let mut o = options(witness_target, &choose);
            o.include = vec![case.to_string()];
            o.faults = FaultSet::of(&[fault.parse::<Fault>().expect("fault")]);
            o.keep_verdicts = true;
            let w = run_quietly(&o).unwrap_or_else(|e| panic!("{witness_target} {case}: {e}"));
            let verdict = w.verdicts.first().map(|(_, v)| *v);
            let inapplicable = INAPPLICABLE
                .iter()
                .any(|(c, k)| choose.iter().any(|x| x == c) && k == case);
            if inapplicable && verdict == Some(Verdict::Skipped) {
                continue;
            }
            // A witness a choice makes the drive refuse (its mnemonic absent): another case that sees the
            // fault, where the choices leave one.
            let also = ALSO_WITNESSED
                .iter()
                .filter(|(f, t, _)| f == fault && t == witness_target)
                .flat_map(|(_, _, cases)| cases.iter());
            let verdict = if verdict == Some(Verdict::Fail) {
                verdict
            } else {
                let mut v = verdict;
                for other in also {
                    o.include = vec![other.to_string()];
                    let w =
                        run_quietly(&o).unwrap_or_else(|e| panic!("{witness_target} {other}: {e}"));
                    if w.verdicts.first().map(|(_, v)| *v) == Some(Verdict::Fail) {
                        v = Some(Verdict::Fail);
                        break;
                    }
                }
                v
            };
            let blind = BLIND_TOGETHER.iter().any(|(f, choices)| {
                f == fault
                    && choices
                        .iter()
                        .all(|c| choose.iter().any(|x| x.starts_with(c)))
            });
            let unchanged = NO_EXCEPTION_TO_CHANGE.iter().any(|(f, c, prefix)| {
                f == fault && c == case && choose.iter().any(|x| x.starts_with(prefix))
            });
            if (blind || unchanged) && verdict == Some(Verdict::Pass) {
                continue;
            }
            if verdict != Some(Verdict::Fail) {
                problems.push(format!(
                    "{witness_target} --choose {} --fault {fault}: witness {case} gives {verdict:?}, expected FAIL",
                    choose.join(" ")
                ));
            }
        }
        (problems, unexercised)
    });
    let problems: Vec<String> = results.iter().flat_map(|(p, _)| p.clone()).collect();
    let unexercised: BTreeSet<(&str, String)> =
        results.iter().flat_map(|(_, u)| u.clone()).collect();
    let listed: BTreeSet<(&str, String)> = NOT_EXERCISED
        .iter()
        .map(|(p, c)| (*p, c.to_string()))
        .collect();
    assert!(
        problems.is_empty() && unexercised == listed,
        "{problems:#?}\nchoices no catalog case shows: {unexercised:#?}\nlisted in NOT_EXERCISED: {listed:#?}\n\
         (update NOT_EXERCISED, or add the case that shows them)"
    );
}

/// A choice the models cannot take is refused, not silently ignored: a close on a drive without Modbus/TCP
/// (every other admissible value of every freedom is simulated).
#[test]
fn a_choice_the_simulator_cannot_take_is_refused() {
    let err = run_quietly(&options("sim:sd2x", &["truncated-pdu=close".to_string()]))
        .expect_err("refused");
    assert!(
        err.to_string().contains("cannot take"),
        "sim:sd2x --choose truncated-pdu=close: unexpected error: {err}"
    );
}

#[test]
fn generated_cases_admit_the_transport_choices() {
    const CHOICES: &[&str] = &[
        "tcp-unit-ids=silence",
        "tcp-unit-ids=exception-0B",
        "tcp-unit-ids=exception-0A",
        "pipelined-response-order=transaction-id",
        "pipelined-server-busy=exception-06",
        "truncated-pdu=silence",
        "truncated-pdu=close",
        "mbap-length-short=silence",
        "mbap-length-short=close",
        "mbap-length-long=close",
        "mbap-length-long=exception-03",
        "pdu-over-253=silence",
        "pdu-over-253=exception-03",
        "exception-check-order=2",
    ];
    // Where the catalog cannot show the choice (requests to units other than 1 and 247, writes among them,
    // MBAP lengths more than one off), these runs must.
    const SHOWN: &[(&str, &str)] = &[
        ("sim:generic", "tcp-unit-ids=silence"),
        ("sim:mdrive", "tcp-unit-ids=silence"),
        ("sim:generic", "tcp-unit-ids=exception-0B"),
        ("sim:mdrive", "tcp-unit-ids=exception-0A"),
        ("sim:generic", "mbap-length-long=exception-03"),
        ("sim:mdrive", "mbap-length-long=close"),
        ("sim:generic", "truncated-pdu=close"),
    ];
    let jobs: Vec<(&str, &str)> = ["sim:generic", "sim:mdrive"]
        .iter()
        .flat_map(|t| CHOICES.iter().map(move |c| (*t, *c)))
        .collect();
    assert_no_problems(jobs, |(target, choice)| {
        let (out, bad) = generated(target, &[choice.to_string()], 300, 5);
        let (id, value) = choice.split_once('=').expect("choice");
        let mut problems = Vec::new();
        if !bad.is_empty() {
            problems.push(format!(
                "{target} --choose {choice} --generated 300 --seed 5: FAIL or NON-STRICT {bad:?}"
            ));
        }
        let shown = out.summary.choices.iter().any(|c| {
            c.freedom == id && (c.value == value || c.changed.iter().any(|(v, _)| v == value))
        });
        if !shown && SHOWN.contains(&(target, choice)) {
            problems.push(format!(
                "{target} --choose {choice}: the choice was not shown"
            ));
        }
        problems
    });
}

/// Generated cases meet the vendor readings, functions served beyond the profile and unit ids with requests
/// no catalog case sends (found by runs against drives with random combinations of choices): a malformed
/// request for a function the drive serves beyond its profile is refused with 03 (App 7), not 01; a 5-byte
/// FC 0x42 is a parameterless command to a drive that expects no byte count, and its unknown mnemonic gets
/// that drive's code; a drive running E/EX/PS/RS by FC 0x41 refuses them by FC 0x42 in generated requests
/// too; a malformed request to another unit id is ignored as a well-formed one is; an MBAP length too long
/// for a function the profile lacks (FC 0x15 with an empty record, which does not decode) is refused with 03
/// where the reference waits for the bytes announced. Each of these FAILed.
#[test]
fn generated_cases_admit_the_vendor_readings_and_extra_functions() {
    let jobs: Vec<(&str, u64, u64, &[&str])> = vec![
        ("sim:sd2x", 1101, 300, &["served-extra-function=served"]),
        ("sim:lmd", 1100, 300, &["served-extra-function=served"]),
        (
            "sim:mdrive",
            1101,
            300,
            &[
                "fc42-parameterless-byte-count=no-count-byte",
                "unknown-mnemonic-exception=4",
            ],
        ),
        (
            "sim:mdrive",
            1102,
            300,
            &["mdrive-program-control-function=fc41"],
        ),
        ("sim:lmd", 2300, 400, &["tcp-unit-ids=silence"]),
        ("sim:mdrive", 9903, 100, &["mbap-length-long=exception-03"]),
        // An SD2x refusing an FC 43 to another node-ID with 03, and checking an FC 08 sub-function before
        // the telegram's size (01), as the independent sd2x-d does: generated bit flips and extensions
        // meet both (seed 7: 4 and 1 cases in 1,000 against that drive, UNIMPLEMENTED and FAIL before).
        (
            "sim:sd2x",
            7,
            1000,
            &[
                "sd2x-fc43-node-id=3",
                "sd2x-diagnostic-data-size=exception-03",
                "sd2x-diagnostic-check-order=1",
            ],
        ),
    ];
    assert_no_problems(jobs, |(target, seed, n, choose)| {
        let choose: Vec<String> = choose.iter().map(|c| c.to_string()).collect();
        let (_, bad) = generated(target, &choose, n, seed);
        (!bad.is_empty()).then(|| {
            format!("{target} --choose {choose:?} --generated {n} --seed {seed}: FAIL or NON-STRICT {bad:?}")
        })
    });
}

/// The LMD's output 4 (coil 0x0003, freedom `lmd-output-4`): FC 01/05 and OT speak of outputs 1-4, OS and
/// O1-O3 of 1-3. A drive with three outputs refuses FC 01/05/0F requests covering coil 0x0003 with 02, and
/// generated coil requests meet it (a drive with four outputs, the reference's choice, FAILed 21 of 3,000
/// such cases before the freedom); both choices pass and the other one is recorded.
#[test]
fn generated_coil_requests_admit_the_lmd_without_output_4() {
    let jobs: Vec<(&str, u64)> = vec![("present", 1), ("exception-02", 1)];
    assert_no_problems(jobs, |(value, seed)| {
        let choose = vec![format!("lmd-output-4={value}")];
        let (out, bad) = generated("sim:lmd", &choose, 300, seed);
        if !bad.is_empty() {
            return Some(format!(
                "sim:lmd --choose {choose:?} --generated 300 --seed {seed}: FAIL or NON-STRICT {bad:?}"
            ));
        }
        let shown = out
            .summary
            .choices
            .iter()
            .any(|c| c.freedom == "lmd-output-4" && c.value == value);
        (!shown).then(|| format!("sim:lmd --choose lmd-output-4={value}: the choice was not shown"))
    });
}

/// A drive that takes a half of a 32-bit register (`partial-register-write=response`) changes state where
/// the reference, refusing halves, does not: it took a half write of SL and slews, and refused the next MR
/// with 04 (busy) where the standing reference took it. That FAILed `gen/3102/82/write-reg`. The reference
/// now follows the outcome the drive showed (the runner's `follows`): it does the step again the drive's
/// way, and keeps to that choice from then on; the drive's choice is still recorded, case by case.
#[test]
fn the_reference_follows_a_drive_that_takes_half_registers() {
    let jobs: Vec<(&str, u64, u64)> = vec![
        ("sim:mdrive", 3102, 400),
        ("sim:lmd", 3102, 400),
        ("sim:mdrive?transport=rtu", 3102, 400),
    ];
    assert_no_problems(jobs, |(target, seed, n)| {
        let choose = vec!["partial-register-write=response".to_string()];
        let (out, bad) = generated(target, &choose, n, seed);
        let shown = out
            .summary
            .choices
            .iter()
            .find(|c| c.freedom == "partial-register-write")
            .map(|c| (c.value.clone(), c.count));
        if !bad.is_empty() {
            return Some(format!(
                "{target} --generated {n} --seed {seed}: FAIL or NON-STRICT {bad:?}"
            ));
        }
        match shown {
            Some((v, count)) if v == "response" && count > 1 => None,
            other => Some(format!(
                "{target}: the choice recorded is {other:?}, not response case after case"
            )),
        }
    });
}

/// Drives taking random combinations of choices (`bench/freedom-combos.py --nonstrict`) were rated
/// NON-STRICT for choices they never changed: the oracle recorded as a choice what was no evidence of one.
/// - `pdu-over-253=exception-03`: a drive skips an ADU over 253 bytes once its bytes are in, so it is
///   silent before then whichever it chose; a generated MBAP length announcing more than was sent was
///   recorded as `silence`.
/// - `lmd-inferred-write-only=rw`: a read of IC and the reserved register beside it is refused (02) for
///   the reserved one; it was recorded as IC being write-only.
/// - `truncated-pdu=silence` on the SD2x: the reference answered the truncated PDUs the drive ignored, so
///   its FC 08 counts drifted from the drive's, and a later count matched another reading of the counter.
///   The reference now follows every outcome the drive shows (silence and exceptions too, not a close).
/// - `lmd-inferred-read-only=rw`: a batch of a write to half of V7 (refused) and a write to I3 (which this
///   drive takes) was judged with the freedoms that decided the whole batch, so the I3 write taken was
///   recorded as the drive taking half writes (`partial-register-write=response`). Each request of a batch
///   is now judged with the freedoms that decide it alone.
/// - `exception-check-order=2` with `lmd-inferred-write-only=rw`: an FC 03 of quantity 0 at S is refused 03;
///   the reference, taking S write-only, took its address for invalid and the 03 for the order of the
///   checks, while this drive, taking S readable, has no address error there. Whether an address at an end
///   of the range is valid is now a reason of its own where it holds an optional or access-free item.
/// - a counter value that two readings give (slave messages = responses sent, when every request was
///   answered) was recorded as the reference's reading.
///
/// Each configuration is run with the catalog and generated cases; each is NON-STRICT with its fix undone
/// (the last one once the reference follows silences).
#[test]
fn choices_are_recorded_from_unambiguous_evidence_only() {
    let jobs: Vec<(&str, u64, &[&str])> = vec![
        ("sim:mdrive", 701, &["pdu-over-253=exception-03"]),
        ("sim:lmd", 5302, &["lmd-inferred-write-only=rw"]),
        ("sim:sd2x", 700, &["truncated-pdu=silence"]),
        ("sim:lmd", 702, &["lmd-inferred-read-only=rw"]),
        (
            "sim:lmd",
            9904,
            &["exception-check-order=2", "lmd-inferred-write-only=rw"],
        ),
        (
            "sim:sd2x",
            5300,
            &[
                "write-read-only-exception=4",
                "exception-check-order=2",
                "truncated-pdu=silence",
                "partial-register-write=exception-04",
                "served-extra-function=served",
                "diagnostic-counter-semantics=slave-count-is-responses-sent",
                "event-counter-clear-counted=counted",
                "sd2x-status-word-bits=111",
                "sd2x-sdo-length-error=0xFFFF0011",
            ],
        ),
    ];
    assert_no_problems(jobs, |(target, seed, choose)| {
        let choose: Vec<String> = choose.iter().map(|c| c.to_string()).collect();
        let (_, bad) = generated_with(target, &choose, 400, seed, true);
        (!bad.is_empty()).then(|| {
            format!("{target} --choose {choose:?} --with-catalog --generated 400 --seed {seed}: FAIL or NON-STRICT {bad:?}")
        })
    });
}

/// `n` generated cases of `seed` against `target` taking `choose`: the run, and the cases it FAILed or rated
/// NON-STRICT.
fn generated(target: &str, choose: &[String], n: u64, seed: u64) -> (RunOutcome, Vec<String>) {
    generated_with(target, choose, n, seed, false)
}

/// [`generated`], with the catalog before the generated cases where `catalog` says so.
fn generated_with(
    target: &str,
    choose: &[String],
    n: u64,
    seed: u64,
    catalog: bool,
) -> (RunOutcome, Vec<String>) {
    let mut o = options(target, choose);
    o.with_catalog = catalog;
    o.generated = n;
    o.seed = Some(seed);
    o.keep_verdicts = true;
    let out = run_quietly(&o).unwrap_or_else(|e| panic!("{target} --choose {choose:?}: {e}"));
    let bad = out
        .verdicts
        .iter()
        .filter(|(_, v)| {
            matches!(
                v,
                Verdict::Fail | Verdict::NonStrict | Verdict::Unimplemented
            )
        })
        .map(|(c, _)| c.clone())
        .collect();
    (out, bad)
}

/// `pipelined-server-busy` followed on its own: a drive with a single transaction (TCP guide 4.4.2.1-2)
/// answers a write pipelined behind a read with exception 06 (Server Busy) and does not take it. The
/// reference, which serves every pipelined request, would have taken it; it follows the drive's choice (the
/// step is done again on it with `exception-06`), so the read-back right after is judged against the
/// register as the drive keeps it. The same case against a drive that serves the whole pipeline shows the
/// write taken, so the read-back does tell the two apart. With the following undone, the read-back FAILs.
#[test]
fn the_reference_follows_a_drive_that_refuses_pipelined_writes_as_busy() {
    use engine::cases::{Case, Compare, Level, Outgoing, Step, Tag};
    use engine::expect::Expectations;
    use engine::observe::Dir;
    use engine::runner::{RunConfig, Runner, Safety, Timing};
    use engine::targets::sim::SimTarget;

    const VALUE: u16 = 0x1234;
    let p = test_support::profile("generic");
    let requirements = Corpus::Embedded.requirements().expect("requirements");
    // Holding register 5: read it, and write VALUE to it right behind, in one segment; then read it back.
    let read = vec![0x03, 0x00, 0x05, 0x00, 0x01];
    let write = [vec![0x06, 0x00, 0x05], VALUE.to_be_bytes().to_vec()].concat();
    let step = |send: Outgoing, compare: Compare| Step::Exchange {
        send,
        compare,
        capture: None,
        note: String::new(),
    };
    let case = Case {
        id: "test/pipeline/write-behind-a-read".into(),
        title: "a write pipelined behind a read, read back".into(),
        reference: "TCP guide 4.2.1.1, 4.4.2.1-2".into(),
        requirement: "test".into(),
        level: Level::Must,
        tags: vec![Tag::TcpOnly, Tag::Write],
        steps: vec![
            step(
                Outgoing::Batch(vec![read.clone(), write]),
                Compare::Structure,
            ),
            step(Outgoing::Pdu(read), Compare::Exact),
        ],
        requirements: vec![],
        freedoms: vec!["pipelined-server-busy".into()],
    };
    for (choice, kept) in [("exception-06", 0u16), ("response", VALUE)] {
        let choose = format!("pipelined-server-busy={choice}");
        let choices =
            drives::Choices::parse_all(&[choose.as_str()], &requirements, &p).expect("choices");
        let drive = drives::Station::new(
            drives::build_with(p.clone(), FaultSet::none(), choices.clone()),
            FaultSet::none(),
            p.device.default_unit,
        )
        .with_choices(choices);
        let cfg = RunConfig {
            unit: 1,
            timing: Timing::default(),
            safety: Safety::default(),
            is_sim: true,
        };
        let reference = SimTarget::new(test_support::station("generic", &[]));
        let mut runner = Runner::new(
            Box::new(SimTarget::new(drive)),
            reference,
            p.clone(),
            cfg,
            Expectations::default(),
        )
        .with_requirements(std::sync::Arc::new(requirements.clone()));
        let r = runner.run_case(&case).expect("run");
        assert_eq!(r.verdict, Verdict::Pass, "{choose}: {r:#?}");
        // The read-back's answer: the register as the drive keeps it.
        let last = r
            .wire
            .iter()
            .rev()
            .find(|w| w.dir == Dir::Rx)
            .expect("an answer");
        assert_eq!(
            last.bytes[last.bytes.len() - 2..],
            kept.to_be_bytes(),
            "{choose}: {last:?}"
        );
        let shown: Vec<_> = runner
            .choices()
            .choices()
            .filter(|c| c.freedom == "pipelined-server-busy")
            .map(|c| c.value.clone())
            .collect();
        let expected: Vec<String> = if choice == "exception-06" {
            vec![choice.into()]
        } else {
            vec![]
        };
        assert_eq!(shown, expected, "{choose}: choices recorded");
    }
}

/// The MDrive's I/O points are inputs by default (manual line 1263) and "the outputs must be configured as
/// such" (lines 532, 579); a drive written from the manual refused FC 05 and FC 10 writes of an output whose
/// point was an input with 04, where the reference takes them, and generated cases FAILed
/// (`mdrive-output-write-while-input`). Each admissible refusal passes the generated cases of that run (seed
/// 1, as found) and the catalog, and shows the choice; the catalog's `profile/mdrive/io-point/*` cases show it
/// too.
#[test]
fn a_drive_refusing_writes_of_outputs_whose_points_are_inputs_passes() {
    refusals_pass(
        "mdrive-output-write-while-input",
        &["exception-04", "exception-03", "exception-02"],
        &["profile/mdrive/io-point/*"],
    );
}

/// The same for reads of an output whose point is configured as an input (`mdrive-output-read-while-input`):
/// the MDrive manual does not say what such a read answers (line 532 says only that the outputs must be
/// configured as such) and gives no exception for it; a drive may serve it (the latch, or 0: what the point
/// drives, see drives' `an_mdrive_output_read_while_its_point_is_an_input_may_read_the_latch_or_zero`), or
/// refuse the read as of an address it does not serve there (02) or as a
/// device failure (04). Each refusal passes the generated cases (seed 1) and the catalog (the golden "read
/// outputs" example and the register reads of O1-O4 meet it), and the run records it.
#[test]
fn a_drive_refusing_reads_of_outputs_whose_points_are_inputs_passes() {
    refusals_pass(
        "mdrive-output-read-while-input",
        &["exception-04", "exception-02"],
        &[],
    );
}

/// Against `sim:mdrive` taking `freedom` = each of `values`: 600 generated cases (seed 1) and the catalog (the
/// cases `include`, or all of it) give no FAIL and no NON-STRICT, and the run records the value as the drive's
/// choice, held to throughout.
fn refusals_pass(freedom: &str, values: &[&str], include: &[&str]) {
    refusals_pass_on("sim:mdrive", freedom, values, include, true);
}

/// [`refusals_pass`] against `target`; the generated cases only where `generated`.
fn refusals_pass_on(
    target: &str,
    freedom: &str,
    values: &[&str],
    include: &[&str],
    generated_too: bool,
) {
    let jobs: Vec<(&str, bool)> = values
        .iter()
        .flat_map(|v| [(*v, false), (*v, true)])
        .filter(|(_, catalog)| *catalog || generated_too)
        .collect();
    assert_no_problems(jobs, |(value, catalog)| {
        let choice = format!("{freedom}={value}");
        let (out, bad) = if catalog {
            let mut o = options(target, std::slice::from_ref(&choice));
            o.include = include.iter().map(|c| c.to_string()).collect();
            o.keep_verdicts = true;
            let out = run_quietly(&o).expect("run");
            let bad: Vec<String> = out
                .verdicts
                .iter()
                .filter(|(_, v)| {
                    matches!(
                        v,
                        Verdict::Fail | Verdict::NonStrict | Verdict::Unimplemented
                    )
                })
                .map(|(c, v)| format!("{c}: {v}"))
                .collect();
            (out, bad)
        } else {
            generated(target, std::slice::from_ref(&choice), 600, 1)
        };
        let mut problems = Vec::new();
        if !bad.is_empty() {
            problems.push(format!("--choose {choice} (catalog: {catalog}): {bad:?}"));
        }
        let shown = out.summary.choices.iter().find(|c| c.freedom == freedom);
        match shown {
            Some(c) if c.value == value && c.changed.is_empty() => {}
            other => problems.push(format!(
                "--choose {choice} (catalog: {catalog}): the choice recorded is {other:?}"
            )),
        }
        problems
    });
}

/// The LMD's output 4 (coil 0x0003): no output setup reaches it (OS: points 1-3, 001 line 1070), so a drive
/// may hold point 4 as an input and refuse writes of it as the MDrive may writes of an output whose point is
/// an input; an LMD built on libmodbus answers them 04 (`lmd-output-4-write`). Each refusal passes the
/// generated cases (seed 1) and the catalog, and the run records it, held to throughout. A refusal with 02
/// once read as output 4 absent (`lmd-output-4`), recorded as nothing where both explained it; the
/// drive read the coil before, so output 4 is there and the refusal is the write's (runner: an explanation
/// that contradicts what the drive showed is set aside where another agrees).
#[test]
fn an_lmd_refusing_writes_of_output_4_passes() {
    refusals_pass_on(
        "sim:lmd",
        "lmd-output-4-write",
        &["exception-04", "exception-03", "exception-02"],
        &[],
        true,
    );
}

/// The SD2x's FC 43 fields "not used" (control bits 0-6, 004 line 608; the address offset, line 627): a drive
/// may leave them alone and serve the telegram (an SD2x built on libmodbus does). The reference taking that
/// choice passes its catalog (whose `profile/sd2x/object/*` cases set them; generated cases do not), and the
/// run records it.
#[test]
fn an_sd2x_leaving_unused_fc43_fields_alone_passes() {
    for freedom in ["sd2x-fc43-control-bits", "sd2x-fc43-offset-nonzero"] {
        refusals_pass_on("sim:sd2x", freedom, &["response"], &[], false);
    }
}

/// Generated cases meet those fields through bit flips, and a drive leaving one alone then answers the rest
/// of the telegram: a write of a read-only object with an offset set gets 000A (read-only), where the
/// reference refusing the offset gives 0008. The model answers the telegram with the field zero on a copy
/// of itself (`unused_field_alternatives`) for the oracle; before it did, 1,000 generated cases (seed 21)
/// against a drive leaving the offset alone FAILed 3 (an SD2x built on libmodbus met the same).
#[test]
fn generated_cases_admit_an_sd2x_leaving_unused_fc43_fields_alone() {
    let jobs = vec![
        ("sd2x-fc43-offset-nonzero", 21),
        ("sd2x-fc43-control-bits", 3),
    ];
    assert_no_problems(jobs, |(freedom, seed)| {
        let choose = vec![format!("{freedom}=response")];
        let (out, bad) = generated("sim:sd2x", &choose, 1000, seed);
        let mut problems = Vec::new();
        if !bad.is_empty() {
            problems.push(format!("--choose {choose:?} --seed {seed}: {bad:?}"));
        }
        match out.summary.choices.iter().find(|c| c.freedom == freedom) {
            Some(c) if c.value == "response" && c.changed.is_empty() => {}
            other => problems.push(format!("--choose {choose:?}: recorded {other:?}")),
        }
        problems
    });
}

/// The reference takes such writes, and the run records that as its choice (so that a drive taking one and
/// refusing another is held to the first: NON-STRICT).
#[test]
fn the_reference_taking_writes_of_outputs_whose_points_are_inputs_is_recorded() {
    let mut o = options("sim:mdrive", &[]);
    o.include = vec!["profile/mdrive/io-point/*".to_string()];
    let out = run_quietly(&o).expect("run");
    let c = out
        .summary
        .choices
        .iter()
        .find(|c| c.freedom == "mdrive-output-write-while-input")
        .expect("the choice recorded");
    assert_eq!((c.value.as_str(), c.count), ("response", 4), "{c:?}");
}

/// The freedom is about points configured as inputs only: a drive that refuses with 04 a write of an output
/// the harness configured as an output FAILs. Here the setup (FC 0x42 S1 = 16, a general purpose output) is
/// acknowledged but not stored (`vendor-write-not-applied`), so the drive refusing writes of input points
/// refuses the coil case's write; the reference, whose point 1 is an output, takes it. The same drive taking
/// such writes passes the case.
#[test]
fn a_drive_refusing_a_write_of_an_output_configured_as_an_output_fails() {
    let case = "profile/mdrive/coil/75-output-1";
    for (choose, expected) in [
        (vec![], Verdict::Pass),
        (
            vec!["mdrive-output-write-while-input=exception-04".to_string()],
            Verdict::Fail,
        ),
    ] {
        let mut o = options("sim:mdrive", &choose);
        o.include = vec![case.to_string()];
        o.faults = FaultSet::of(&[Fault::VendorWriteNotApplied]);
        o.keep_verdicts = true;
        let out = run_quietly(&o).expect("run");
        assert_eq!(
            out.verdicts
                .iter()
                .map(|(c, v)| (c.as_str(), *v))
                .collect::<Vec<_>>(),
            vec![(case, expected)],
            "--choose {choose:?}"
        );
    }
}

/// A drive whose own quantity limit lies between its manual's and the specification's (an independent MDrive,
/// tests/independent/mdrive-g, DECISIONS.md item 3: 4 registers to write, where the manual's prose gives 2).
/// It takes FC 16 of 3 or 4 registers to the checks after the quantity's and refuses a value above its
/// maximum there, with its own code (04, `value-out-of-range`), where the reference refuses the quantity
/// (03). The station offers the answer the request would get served (`quantity-over-device-limit-served`),
/// and the code of the refusal it then meets is the drive's choice too; whether a quantity is served is
/// about that quantity. Before, `gen/131/478/write-span` FAILed against that drive, and against this one;
/// a refusal with 02 or 03 on the way of a served request is still taken as a refusal of the quantity.
#[test]
fn a_drive_whose_own_quantity_limit_is_above_its_manuals_passes() {
    let dir = test_support::TempDir::new("limit4");
    let corpus = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../../corpus/profiles/mdrive.toml"
    );
    let text = std::fs::read_to_string(corpus).expect("mdrive profile");
    let limit2 = "code = 0x10\nname = \"Write Multiple Registers\"\nmax_quantity = 2\n";
    assert!(
        text.contains(limit2),
        "the MDrive profile's FC 16 limit moved"
    );
    let path = dir.path().join("mdrive-limit4.toml");
    std::fs::write(&path, text.replace(limit2, &limit2.replace("= 2", "= 4"))).expect("write");
    let target = format!("sim:{}", path.display());
    let choose: Vec<String> = ["value-out-of-range=4", "write-read-only-exception=4"]
        .iter()
        .map(|c| c.to_string())
        .collect();
    let mut o = options(&target, &choose);
    o.profile = Some("mdrive".into());
    o.generated = 1000;
    o.seed = Some(131);
    o.keep_verdicts = true;
    let out = run_quietly(&o).unwrap_or_else(|e| panic!("{target}: {e}"));
    let bad: Vec<_> = out
        .verdicts
        .iter()
        .filter(|(_, v)| matches!(v, Verdict::Fail | Verdict::NonStrict))
        .collect();
    assert!(bad.is_empty(), "FAIL or NON-STRICT: {bad:?}");
    // The drive's codes are recorded, and no choice changes (a refusal of a served quantity taken for the
    // quantity's refusal would show `quantity-over-device-limit` changing its mind).
    let changed: Vec<_> = out
        .summary
        .choices
        .iter()
        .filter(|c| !c.changed.is_empty())
        .collect();
    assert!(changed.is_empty(), "choices changed: {changed:?}");
    assert!(
        out.summary
            .choices
            .iter()
            .any(|c| c.freedom == "value-out-of-range" && c.value == "4"),
        "value-out-of-range = 4 not recorded: {:?}",
        out.summary.choices
    );
}

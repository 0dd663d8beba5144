//! `probe` on the wire: against every reference drive, a default probe sends no request with a write function
//! code (nor anything the safety classifier rates as a write); `--probe-writes` sends write codes only in
//! requests every drive rejects; and the draft a probe writes loads, claims no width or access, and gives a
//! catalog without a single writing case.

use std::time::Duration;

use codec::{Framing, Response};
use drives::profile::Profile;
use drives::{FaultSet, Station};
use engine::cases::Tag;
use engine::cases::catalog;
use engine::cases::generated::pdu_tags;
use engine::probe::{self, ProbeOptions, ProbeReport, WRITE_PROBES, draft};
use engine::targets::sim::SimTarget;
use engine::targets::{Received, Target, TargetError, TargetUrl};
use test_support::profile;

/// A target that keeps every frame sent and every observation received.
struct Recording {
    inner: SimTarget,
    sent: Vec<Vec<u8>>,
    received: Vec<Received>,
}

impl Target for Recording {
    fn framing(&self) -> Framing {
        self.inner.framing()
    }
    fn now(&self) -> Duration {
        self.inner.now()
    }
    fn send(&mut self, bytes: &[u8]) -> Result<(), TargetError> {
        self.sent.push(bytes.to_vec());
        self.inner.send(bytes)
    }
    fn recv(&mut self, timeout: Duration) -> Result<Received, TargetError> {
        let r = self.inner.recv(timeout)?;
        self.received.push(r.clone());
        Ok(r)
    }
    fn idle(&mut self, d: Duration) {
        self.inner.idle(d)
    }
    fn reconnect(&mut self) -> Result<(), TargetError> {
        self.inner.reconnect()
    }
    fn drain(&mut self) {
        self.inner.drain()
    }
    fn describe(&self) -> String {
        self.inner.describe()
    }
}

/// (sim URL, profile, framing, scan) of every reference drive on both framings.
const DRIVES: &[(&str, &str, Framing, (u16, u16))] = &[
    ("sim:mdrive", "mdrive", Framing::Tcp, (0, 0xC0)),
    ("sim:lmd", "lmd", Framing::Tcp, (0, 0xC0)),
    ("sim:sd2x", "sd2x", Framing::Rtu, (1995, 2040)),
    ("sim:sd2x?transport=tcp", "sd2x", Framing::Tcp, (1995, 2040)),
    ("sim:generic", "generic", Framing::Tcp, (0, 0x70)),
    (
        "sim:generic?transport=rtu",
        "generic",
        Framing::Rtu,
        (0, 0x70),
    ),
];

fn probe_of(
    name: &str,
    framing: Framing,
    scan: (u16, u16),
    writes: bool,
) -> (ProbeReport, Recording) {
    let p = profile(name);
    let unit = p.device.default_unit;
    let station = Station::new(drives::build(p, FaultSet::none()), FaultSet::none(), unit);
    let mut t = Recording {
        inner: SimTarget::with_framing(station, framing, None),
        sent: Vec::new(),
        received: Vec::new(),
    };
    let report = probe::probe(
        &mut t,
        &ProbeOptions {
            unit,
            timeout: Duration::from_millis(500),
            scan,
            writes,
            unread: probe::unread_of(&profile(name)),
        },
    )
    .expect("probe");
    (report, t)
}

/// The PDU of a request frame.
fn pdu_of(framing: Framing, frame: &[u8]) -> &[u8] {
    match framing {
        Framing::Rtu => &frame[1..frame.len() - 2],
        _ => &frame[7..],
    }
}

/// Function codes that write (or may, for the vendor codes) on some drive.
const WRITE_CODES: [u8; 10] = [0x05, 0x06, 0x0F, 0x10, 0x15, 0x16, 0x17, 0x41, 0x42, 0x43];

#[test]
fn a_default_probe_sends_no_write_function_code() {
    for (url, name, framing, scan) in DRIVES {
        let (report, t) = probe_of(name, *framing, *scan, false);
        let p = profile(name);
        assert_eq!(
            report.requests,
            t.sent.len(),
            "{url}: every request counted"
        );
        assert_eq!(report.write_requests, 0, "{url}");
        assert!(
            t.sent.len() > 40,
            "{url}: the probe ran ({} requests)",
            t.sent.len()
        );
        for frame in &t.sent {
            let pdu = pdu_of(*framing, frame);
            let fc = pdu[0];
            assert!(
                !WRITE_CODES.contains(&fc),
                "{url}: FC 0x{fc:02X} sent: {pdu:02X?}"
            );
            if fc == 0x08 {
                assert_eq!(
                    &pdu[1..3],
                    &[0, 0],
                    "{url}: FC 08 only as Return Query Data"
                );
            }
            let tags = pdu_tags(&p, pdu);
            assert!(
                !tags.contains(&Tag::Write) && !tags.contains(&Tag::Destructive),
                "{url}: the safety classifier rates {pdu:02X?} {tags:?}"
            );
        }
        assert!(
            report.refused.is_empty(),
            "{url}: refused {:?}",
            report.refused
        );
        let text = probe::render(&report, Some(&p), *scan);
        assert!(text.contains("none of them writes"), "{url}: {text}");
        assert!(
            text.contains("not probed (write code: --probe-writes)"),
            "{url}: {text}"
        );
    }
}

#[test]
fn probe_writes_sends_write_codes_only_in_requests_every_drive_rejects() {
    for (url, name, framing, scan) in DRIVES {
        let (report, t) = probe_of(name, *framing, *scan, true);
        assert_eq!(
            report.write_requests, 5,
            "{url}: FC 05, 0F, 10, 17 and 42 once each"
        );
        let mut writes = 0;
        for (frame, answer) in t.sent.iter().zip(&t.received) {
            let pdu = pdu_of(*framing, frame);
            let fc = pdu[0];
            assert_ne!(fc, 0x06, "{url}: FC 06 is never sent");
            if !WRITE_PROBES.contains(&fc) {
                continue;
            }
            writes += 1;
            let Received::Frame { bytes, .. } = answer else {
                panic!("{url}: no answer to {pdu:02X?}: {answer:?}");
            };
            let decoded = codec::decode_any(bytes, *framing, codec::Direction::Response)
                .expect("the answer decodes");
            assert!(
                matches!(decoded.pdu, codec::Pdu::Response(ref r) if r.is_exception()),
                "{url}: {pdu:02X?} was not rejected: {:?}",
                decoded.pdu
            );
        }
        assert_eq!(
            writes, 6,
            "{url}: the 5 write codes and the vendor read 0x41"
        );
        assert!(probe::render(&report, None, *scan).contains("must reject before writing"));
    }
    // Nothing was written: coil 0 (where FC 05 asked for 0x1234) is still off.
    let (_, mut t) = probe_of("generic", Framing::Tcp, (0, 0x70), true);
    let mut frame = Vec::new();
    codec::tcp::encode_adu(7, 1, &[0x01, 0, 0, 0, 1], &mut frame).expect("frame");
    t.send(&frame).expect("send");
    let Received::Frame { bytes, .. } = t.recv(Duration::from_millis(500)).expect("recv") else {
        panic!("no answer to the coil read");
    };
    let decoded =
        codec::decode_any(&bytes, Framing::Tcp, codec::Direction::Response).expect("decodes");
    assert_eq!(
        decoded.pdu,
        codec::Pdu::Response(Response::ReadCoils { data: vec![0] }),
        "coil 0 untouched"
    );
}

#[test]
fn a_draft_loads_claims_no_width_or_access_and_its_catalog_never_writes() {
    for (url, name, framing, scan) in DRIVES {
        let (report, _) = probe_of(name, *framing, *scan, false);
        let target = TargetUrl::parse(url).expect("url");
        let unit = profile(name).device.default_unit;
        let text = draft::write(&report, &target, unit, *scan);
        let d =
            Profile::parse("draft.toml", &text).unwrap_or_else(|e| panic!("{url}: {e}\n{text}"));
        for key in [
            "width",
            "access",
            "min",
            "max",
            "default",
            "motion",
            "destructive",
        ] {
            assert!(
                !text.lines().any(|l| l.starts_with(&format!("{key} "))),
                "{url}: the draft claims `{key}`:\n{text}"
            );
        }
        assert!(d.draft.is_some(), "{url}: [draft] records the probe");
        assert!(!d.registers.is_empty(), "{url}: registers found");
        assert!(d.registers.iter().all(|r| !r.get_ref().confirmed));
        assert!(
            d.coils
                .iter()
                .chain(&d.discrete_inputs)
                .all(|b| !b.get_ref().confirmed)
        );
        assert!(d.functions.iter().all(|f| !f.confirmed));
        assert!(d.identification.iter().all(|o| !o.confirmed));
        assert_eq!(d.device.transports.len(), 1);
        let cases = catalog::build(&d, None, *framing, unit);
        let writing: Vec<&str> = cases
            .iter()
            .filter(|c| c.has(Tag::Write))
            .map(|c| c.id.as_str())
            .collect();
        assert!(
            writing.is_empty(),
            "{url}: the draft's catalog writes: {writing:?}"
        );
        assert!(
            cases.iter().any(|c| c.id.contains("/read/")),
            "{url}: the registers are read"
        );
    }
}

/// A register whose read clears it (MCode ER, "must be read or set to 0 to clear": the profile's
/// `read_clears`) is left unread by the probe, said so, and not counted as a difference from the profile;
/// without the profile's list the probe reads it (and the classifier rates that read destructive).
#[test]
fn the_probe_leaves_a_register_a_read_clears_unread() {
    let p = profile("mdrive");
    let er = p
        .registers
        .iter()
        .map(|r| r.get_ref())
        .find(|r| r.read_clears)
        .expect("a read_clears register")
        .address;
    let (report, t) = probe_of("mdrive", Framing::Tcp, (0, 0xC0), false);
    assert_eq!(report.unread, [er]);
    let read_of_er = |t: &Recording| {
        t.sent.iter().any(|f| {
            let pdu = pdu_of(Framing::Tcp, f);
            pdu[0] == 0x03 && u16::from_be_bytes([pdu[1], pdu[2]]) == er
        })
    };
    assert!(!read_of_er(&t));
    let text = probe::render(&report, Some(&p), (0, 0xC0));
    assert!(text.contains(&format!("not read: 0x{er:04X}")), "{text}");
    let holding = text
        .split("holding (FC 03)")
        .nth(1)
        .and_then(|s| s.lines().nth(4))
        .unwrap_or("");
    assert_eq!(holding.trim(), "same", "{text}");
    // Without the list (no profile given): read, and rated destructive.
    let station = Station::new(
        drives::build(p.clone(), FaultSet::none()),
        FaultSet::none(),
        255,
    );
    let mut t = Recording {
        inner: SimTarget::with_framing(station, Framing::Tcp, None),
        sent: Vec::new(),
        received: Vec::new(),
    };
    let o = ProbeOptions {
        unit: p.device.default_unit,
        timeout: Duration::from_millis(500),
        scan: (0, 0xC0),
        writes: false,
        unread: vec![],
    };
    let report = probe::probe(&mut t, &o).expect("probe");
    assert!(report.unread.is_empty());
    assert!(read_of_er(&t));
}

/// Behind a gateway (the SD2x over Modbus/TCP, the simulated gateway answering 0B where the drive is silent
/// and the other unit ids refused 0A), the other unit ids' 0A/0B are not answers of a drive there: the probe
/// reports them as refused as a gateway refuses an id with no device behind it, and the draft's unit ids
/// stay the drive's own. (Before, 247 and 255 were "answered", and a draft would take them for the drive's.)
#[test]
fn a_gateways_refusal_of_another_unit_id_is_no_answer_of_a_drive_there() {
    use drives::corpus::Corpus;
    let p = profile("sd2x");
    let unit = p.device.default_unit;
    let requirements = Corpus::Embedded.requirements().expect("requirements");
    let choose = [
        "gateway-no-response=exception-0B",
        "tcp-unit-ids=exception-0A",
    ];
    let choices = drives::Choices::parse_all(&choose, &requirements, &p).expect("choices");
    let station = Station::new(
        drives::build_with(p.clone(), FaultSet::none(), choices.clone()),
        FaultSet::none(),
        unit,
    )
    .with_choices(choices);
    let mut t = SimTarget::with_framing(station, Framing::Tcp, None);
    let report = probe::probe(
        &mut t,
        &ProbeOptions {
            unit,
            timeout: Duration::from_millis(500),
            scan: (1995, 2040),
            writes: false,
            unread: probe::unread_of(&p),
        },
    )
    .expect("probe");
    assert!(
        report.units.iter().all(|(_, answered)| !answered),
        "{:?}",
        report.units
    );
    let mut refused = report.gateway_refused.clone();
    refused.sort_unstable();
    assert_eq!(refused, [(0, 0x0B), (247, 0x0A), (255, 0x0B)]);
    let text = probe::render(&report, Some(&p), (1995, 2040));
    assert!(
        text.contains("refused as a gateway refuses") && text.contains("247 (0x0A)"),
        "{text}"
    );
    let url = TargetUrl::parse("tcp://127.0.0.1:502").expect("url");
    let d = draft::write(&report, &url, unit, (1995, 2040));
    assert!(d.contains("unit_ids = [1, 1]"), "{d}");
}

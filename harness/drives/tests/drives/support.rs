//! What the drives' tests share: corpus profiles, a Modbus/TCP client view of a station on a virtual clock,
//! hex helpers, the exchange tables of tests/data/exchanges.toml, and the property that no request makes a
//! station panic or answer something that does not decode.

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::sync::{Mutex, OnceLock};
use std::time::Duration;

use codec::tcp::{self, MBAP_LEN};
use codec::{Pdu, Request, Response, hex_spaced, parse_hex};
use drives::corpus::Corpus;
use drives::profile::Profile;
use drives::{self, Fault, FaultSet, Station};
use proptest::prelude::*;
use serde::Deserialize;

/// shared/seeds/ beside the repository (the developers' and CI's layout), or MODBUS_HARNESS_SEEDS: the
/// manuals whose lines the requirements and the safety flags cite.
pub fn seeds_dir() -> Option<PathBuf> {
    if let Ok(d) = std::env::var("MODBUS_HARNESS_SEEDS") {
        return Some(PathBuf::from(d));
    }
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../..");
    [root.join("../shared/seeds"), root.join("shared/seeds")]
        .into_iter()
        .find(|d| d.is_dir())
}

/// A profile of the embedded corpus, or of tests/data/ for a stem `data/NAME` (tests/data/NAME.toml), parsed
/// once per test binary (the profiles are large and the property tests build many stations).
pub fn profile(stem: &str) -> Profile {
    static PARSED: OnceLock<Mutex<BTreeMap<String, Profile>>> = OnceLock::new();
    let parsed = PARSED.get_or_init(Default::default);
    if let Some(p) = parsed.lock().unwrap().get(stem) {
        return p.clone();
    }
    let (name, text) = match stem.strip_prefix("data/") {
        Some(file) => {
            let path = format!("{}/tests/data/{file}.toml", env!("CARGO_MANIFEST_DIR"));
            let text =
                std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("read {path}: {e}"));
            (path, text)
        }
        None => Corpus::Embedded
            .file("profiles", stem)
            .unwrap_or_else(|e| panic!("profile {stem} in the embedded corpus: {e}")),
    };
    let p = Profile::parse(&name, &text).unwrap_or_else(|e| panic!("{e}"));
    parsed.lock().unwrap().insert(stem.to_string(), p.clone());
    p
}

/// Hex as the tests compare it: upper case, one space between bytes.
pub fn hex(s: &str) -> String {
    hex_spaced(&parse_hex(s).expect("hex"))
}

/// The bytes of `s` as hex.
pub fn ascii_hex(s: &str) -> String {
    hex_spaced(s.as_bytes())
}

/// A station with its model, a Modbus/TCP client view and a virtual clock.
pub struct Sim {
    pub station: Station,
    pub unit: u8,
    tid: u16,
    now: Duration,
}

/// A fault-free station of the corpus profile `stem` taking `choose` (`FREEDOM=VALUE`), as
/// `simulate --choose` builds it.
pub fn chosen_station(stem: &str, choose: &[&str]) -> Station {
    let p = profile(stem);
    let requirements = Corpus::Embedded.requirements().expect("requirements");
    let choices = drives::Choices::parse_all(choose, &requirements, &p).expect("choices");
    let unit = p.device.default_unit;
    Station::new(
        drives::build_with(p, FaultSet::none(), choices.clone()),
        FaultSet::none(),
        unit,
    )
    .with_choices(choices)
}

impl Sim {
    /// A station for `p` with `faults`, answering as the profile's default unit.
    pub fn with(p: Profile, faults: &[Fault]) -> Self {
        let unit = p.device.default_unit;
        let f = FaultSet::of(faults);
        Self {
            station: Station::new(drives::build(p, f.clone()), f, unit),
            unit,
            tid: 0,
            now: Duration::ZERO,
        }
    }

    /// A station for the corpus profile `stem`.
    pub fn new(stem: &str, faults: &[Fault]) -> Self {
        Self::with(profile(stem), faults)
    }

    /// Move the virtual clock to `ms` milliseconds.
    pub fn at_ms(&mut self, ms: u64) -> &mut Self {
        self.now = Duration::from_millis(ms);
        self
    }

    /// Send one request PDU; the response PDU. Checks the MBAP echo on the way.
    pub fn pdu(&mut self, pdu: &[u8]) -> Vec<u8> {
        self.tid = self.tid.wrapping_add(1);
        let req = Request::decode(pdu).unwrap_or_else(|e| panic!("test request decodes: {e}"));
        let adu = tcp::encode(self.tid, self.unit, &Pdu::Request(req)).expect("encodes");
        let wire = self
            .station
            .tcp_adu(self.now, &adu)
            .expect("the drive answers");
        let hdr = tcp::Mbap::parse(&wire.bytes).expect("MBAP header");
        assert_eq!(hdr.transaction_id, self.tid, "transaction id echoed");
        assert_eq!(hdr.unit_id, self.unit, "unit id echoed");
        assert_eq!(usize::from(hdr.length), wire.bytes.len() - 6, "MBAP length");
        wire.bytes[MBAP_LEN..].to_vec()
    }

    /// Send a request PDU given as hex; the response PDU as upper-case spaced hex.
    pub fn ask(&mut self, pdu_hex: &str) -> String {
        let pdu = parse_hex(pdu_hex).expect("hex");
        hex_spaced(&self.pdu(&pdu))
    }

    /// Send any PDU bytes as request `i` at `now`: the station must not panic, and an answer must decode
    /// strictly and echo the function code.
    pub fn answer_decodes(
        &mut self,
        i: usize,
        now: Duration,
        pdu: &[u8],
    ) -> Result<(), TestCaseError> {
        let mut adu = Vec::new();
        let Ok(()) = tcp::encode_adu(i as u16, self.unit, pdu, &mut adu) else {
            return Ok(());
        };
        let Some(w) = self.station.tcp_adu(now, &adu) else {
            return Ok(());
        };
        let body = &w.bytes[MBAP_LEN..];
        let resp = Response::decode(body);
        prop_assert!(
            resp.is_ok(),
            "PDU {} answered {}: {:?}",
            hex_spaced(pdu),
            hex_spaced(body),
            resp
        );
        if let (Some(&fc), Some(&rfc)) = (pdu.first(), body.first()) {
            prop_assert_eq!(rfc & 0x7F, fc & 0x7F, "function code echoed");
        }
        Ok(())
    }
}

/// The faults that change what the MDrive/LMD and generic models answer (the wire-level ones are the station's and tested there);
/// under them too, nothing may panic and every answer must decode.
pub const MODEL_FAULTS: &[Fault] = &[
    Fault::WordOrder,
    Fault::ReservedReadable,
    Fault::ReadOnlyWritable,
    Fault::RangeUnchecked,
    Fault::QuantityUnchecked,
    Fault::IllegalCoilValueAccepted,
    Fault::QuantityLowByte,
    Fault::QuantityOverSpecDropped,
];

/// The answers of a healthy drive and of one with `fault` (both fresh, for profile `p`) to `pdus` in order.
pub fn both(p: &Profile, fault: Fault, pdus: &[&str]) -> (Vec<String>, Vec<String>) {
    let mut ok = Sim::with(p.clone(), &[]);
    let mut bad = Sim::with(p.clone(), &[fault]);
    (
        pdus.iter().map(|r| ok.ask(r)).collect(),
        pdus.iter().map(|r| bad.ask(r)).collect(),
    )
}

/// A healthy drive answers `pdus` (in order) with `healthy`, and one with `fault` with `faulty` ([`both`]).
pub fn assert_fault_shows(
    p: &Profile,
    fault: Fault,
    pdus: &[&str],
    healthy: &[&str],
    faulty: &[&str],
) {
    let (ok, bad) = both(p, fault, pdus);
    assert_eq!(ok, healthy, "{fault}: the healthy drive");
    assert_eq!(bad, faulty, "{fault}: the drive with the fault");
}

// ---------------------------------------------------------------------------------------------------------------
// Exchange tables (tests/data/exchanges.toml)
// ---------------------------------------------------------------------------------------------------------------

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct Exchanges {
    table: Vec<Table>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct Table {
    name: String,
    profiles: Vec<String>,
    exchanges: Vec<Exchange>,
}

/// `[request, response]` or `[request, response, why]`.
#[derive(Deserialize)]
#[serde(untagged)]
enum Exchange {
    Plain(String, Answer),
    Why(String, Answer, String),
}

/// The response PDU, the same for every profile of the table or one per profile.
#[derive(Deserialize)]
#[serde(untagged)]
enum Answer {
    Same(String),
    PerProfile(BTreeMap<String, String>),
}

fn exchange_tables() -> Vec<Table> {
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/data/exchanges.toml");
    let text = std::fs::read_to_string(path).unwrap_or_else(|e| panic!("read {path}: {e}"));
    let file: Exchanges = toml::from_str(&text).unwrap_or_else(|e| panic!("parse {path}: {e}"));
    file.table
}

/// The names of the tables of tests/data/exchanges.toml.
pub fn exchange_table_names() -> Vec<String> {
    exchange_tables().into_iter().map(|t| t.name).collect()
}

/// Run table `name` of tests/data/exchanges.toml: for each of its profiles a fresh drive gets the table's
/// requests in order, and must give each response byte for byte. Fails naming every exchange answered
/// otherwise; returns the drives afterwards, with their profiles, for checks of their state.
pub fn run_exchanges(name: &str) -> Vec<(String, Sim)> {
    let table = exchange_tables()
        .into_iter()
        .find(|t| t.name == name)
        .unwrap_or_else(|| panic!("no table `{name}` in tests/data/exchanges.toml"));
    let mut failed = Vec::new();
    let mut sims = Vec::new();
    for stem in &table.profiles {
        let mut s = Sim::new(stem, &[]);
        for (i, x) in table.exchanges.iter().enumerate() {
            let (request, answer, why) = match x {
                Exchange::Plain(r, a) => (r, a, ""),
                Exchange::Why(r, a, w) => (r, a, w.as_str()),
            };
            let want = match answer {
                Answer::Same(w) => w,
                Answer::PerProfile(by) => by
                    .get(stem)
                    .unwrap_or_else(|| panic!("{name} #{}: no response for {stem}", i + 1)),
            };
            let got = s.ask(request);
            if got != hex(want) {
                failed.push(format!(
                    "#{} {stem}: {request} answered {got}, want {want} ({why})",
                    i + 1
                ));
            }
        }
        sims.push((stem.clone(), s));
    }
    assert!(
        failed.is_empty(),
        "{} exchange(s) of table {name} answered otherwise:\n  {}",
        failed.len(),
        failed.join("\n  ")
    );
    sims
}

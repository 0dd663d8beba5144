//! Values a manual gives two ways: the harness sends only what every reading of the manual takes (a register's
//! `safe_values`, a diagnostic's `data_bytes`; corpus/profiles/SCHEMA.md). Found with drives written
//! independently from the manuals: TE (trip enable) is printed 0-43 with bits summing to 63, most of them
//! reserved, and one such MDrive takes only 0 and 16; the SD2x's FC 08 telegram "has always the same size".

use codec::{Framing, Request};
use drives::corpus::Corpus;
use engine::cases::catalog;
use engine::cases::generated::Generator;
use engine::{Case, Outgoing, Step};
use test_support::profile;

/// Every value a case writes to holding register `address` with a well-formed FC 06 / FC 10.
fn written_to(c: &Case, address: u16) -> Vec<i64> {
    let mut out = Vec::new();
    for s in &c.steps {
        let Step::Exchange {
            send: Outgoing::Pdu(pdu) | Outgoing::PduToUnit { pdu, .. },
            ..
        } = s
        else {
            continue;
        };
        match Request::decode(pdu) {
            Ok(Request::WriteSingleRegister { address: a, value }) if a == address => {
                out.push(i64::from(value));
            }
            Ok(Request::WriteMultipleRegisters { address: a, values })
                if a <= address && usize::from(address - a) < values.len() =>
            {
                out.push(i64::from(values[usize::from(address - a)]));
            }
            _ => {}
        }
    }
    out
}

/// TE (0x007D) of the MDrive and the LMD: in range, only 0 or 16 are written, whatever the case source; out
/// of range, only values above 63 (refused by every reading). And both kinds are written, so the check bites.
#[test]
fn trip_enable_is_written_only_with_values_every_reading_takes() {
    for name in ["mdrive", "lmd"] {
        let p = profile(name);
        let te = p
            .registers
            .iter()
            .map(|r| r.get_ref())
            .find(|r| r.mnemonic.as_deref() == Some("TE"))
            .expect("TE");
        assert_eq!(te.safe_values, [0, 16], "{name}");
        assert_eq!(te.range(), (0, 63), "{name}: the widest reading");
        let unit = p.device.default_unit;
        let golden = Corpus::Embedded.golden(name).expect("golden");
        let mut cases = catalog::build(&p, golden.as_ref(), Framing::Tcp, unit);
        cases.extend(Generator::new(&p, unit, 1).cases(20_000));
        let values: Vec<(String, i64)> = cases
            .iter()
            .flat_map(|c| {
                written_to(c, te.address)
                    .into_iter()
                    .map(|v| (c.id.clone(), v))
            })
            .collect();
        let disputed: Vec<&(String, i64)> = values
            .iter()
            .filter(|(_, v)| (1..=63).contains(v) && *v != 16)
            .collect();
        assert!(disputed.is_empty(), "{name}: {disputed:?}");
        assert!(values.iter().any(|(_, v)| *v == 16), "{name}: {values:?}");
        assert!(values.iter().any(|(_, v)| *v > 63), "{name}: {values:?}");
    }
}

/// The SD2x's FC 08/00 echo case sends the one data word its manual's telegram has; the generic profile's
/// (any number of words, spec 6.8.1) sends two words.
#[test]
fn the_echo_case_sends_the_data_size_the_manual_fixes() {
    for (name, bytes) in [("sd2x", 2usize), ("generic", 4)] {
        let p = profile(name);
        let golden = Corpus::Embedded.golden(name).expect("golden");
        let framing = if name == "sd2x" {
            Framing::Rtu
        } else {
            Framing::Tcp
        };
        let cases = catalog::build(&p, golden.as_ref(), framing, p.device.default_unit);
        let echo = cases
            .iter()
            .find(|c| c.id == "spec/app-6.8.1/00-return-query-data")
            .expect("the echo case");
        let Some(Step::Exchange {
            send: Outgoing::Pdu(pdu),
            ..
        }) = echo.steps.first()
        else {
            panic!("{echo:?}");
        };
        match Request::decode(pdu) {
            Ok(Request::Diagnostics { data, .. }) => assert_eq!(data.len(), bytes, "{name}"),
            other => panic!("{name}: {other:?}"),
        }
    }
}

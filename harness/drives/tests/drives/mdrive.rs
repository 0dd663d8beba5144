//! The MDrive/LMD reference model driven through the `Station` over Modbus/TCP with a virtual clock:
//! golden replay of the manuals' examples, the register map's address/access/range rules, VI < VM, motion over
//! time, the vendor mnemonics, device identification, each model-level fault against the healthy drive, and a
//! property test that no request PDU makes the station panic or answer something that does not decode.
//!
//! Proptest prints the failing seed and persists it under `proptest-regressions/`; rerunning replays it.

use std::time::Duration;

use codec::{ExceptionCode, FunctionCode, Mnemonic, Request, Response, hex_spaced, parse_hex};
use drives::corpus::Corpus;
use drives::golden::GoldenFile;
use drives::models::mdrive::{Mdrive, Program};
use drives::profile::WordOrder;
use drives::{self, DriveModel, Fault, FaultSet};
use proptest::collection::vec;
use proptest::prelude::*;
use proptest::sample::{select, subsequence};

use crate::support::{
    MODEL_FAULTS, Sim, ascii_hex, assert_fault_shows, both, chosen_station, hex, profile,
    run_exchanges,
};

/// The MDrive/LMD registers and mnemonics through the client view.
impl Sim {
    fn word_order(&self) -> WordOrder {
        self.station.profile().device.word_order
    }

    /// Read a 32-bit register pair at `address` as a signed value, in the profile's word order.
    fn read32(&mut self, address: u16) -> i32 {
        let r = self.pdu(&[0x03, (address >> 8) as u8, address as u8, 0, 2]);
        assert_eq!(&r[..2], &[0x03, 0x04], "read of 0x{address:04X}");
        let a = u16::from_be_bytes([r[2], r[3]]);
        let b = u16::from_be_bytes([r[4], r[5]]);
        self.word_order().join(a, b) as i32
    }

    /// Read one 16-bit register.
    fn read16(&mut self, address: u16) -> u16 {
        let r = self.pdu(&[0x03, (address >> 8) as u8, address as u8, 0, 1]);
        assert_eq!(&r[..2], &[0x03, 0x02], "read of 0x{address:04X}");
        u16::from_be_bytes([r[2], r[3]])
    }

    /// Write a 32-bit value with FC 16 in the profile's word order; the response PDU as hex.
    fn write32(&mut self, address: u16, value: i32) -> String {
        let [a, b] = self.word_order().split(value as u32);
        let mut p = vec![0x10, (address >> 8) as u8, address as u8, 0, 2, 4];
        p.extend_from_slice(&a.to_be_bytes());
        p.extend_from_slice(&b.to_be_bytes());
        hex_spaced(&self.pdu(&p))
    }

    /// Write one 16-bit register with FC 16 (the drives have no FC 06).
    fn write16(&mut self, address: u16, value: u16) -> String {
        let mut p = vec![0x10, (address >> 8) as u8, address as u8, 0, 1, 2];
        p.extend_from_slice(&value.to_be_bytes());
        hex_spaced(&self.pdu(&p))
    }

    /// FC 0x42 with `params`; the response PDU as hex.
    fn vendor_write(&mut self, name: &str, params: &str) -> String {
        let req = Request::VendorWrite {
            mnemonic: Mnemonic::from_name(name).expect("mnemonic"),
            params: params.as_bytes().to_vec(),
        };
        hex_spaced(&self.pdu(&req.to_bytes().expect("encodes")))
    }

    /// FC 0x41; the parameter string, or the exception response as hex.
    fn vendor_read(&mut self, name: &str) -> Result<String, String> {
        let req = Request::VendorRead {
            mnemonic: Mnemonic::from_name(name).expect("mnemonic"),
        };
        let r = self.pdu(&req.to_bytes().expect("encodes"));
        match Response::decode(&r) {
            Ok(Response::VendorRead { params }) => Ok(String::from_utf8_lossy(&params).into()),
            _ => Err(hex_spaced(&r)),
        }
    }
}

// ---------------------------------------------------------------------------------------------------------------
// Golden replay: every corrected request of the manuals, each on a factory-fresh drive (the examples are
// independent of each other), gives the corrected response; requests printed without a response are accepted.
// ---------------------------------------------------------------------------------------------------------------

fn golden_replay(stem: &str) {
    let (name, text) = Corpus::Embedded.file("golden", stem).expect("golden file");
    let golden = GoldenFile::parse(&name, &text).unwrap_or_else(|e| panic!("{e}"));
    let (mut replayed, mut compared) = (0, 0);
    for req in golden
        .frames
        .iter()
        .filter(|f| f.request.is_none() && f.direction == drives::golden::GoldenDirection::Request)
    {
        let bytes = req
            .corrected
            .as_deref()
            .or(req.printed.as_deref())
            .unwrap_or_else(|| panic!("{}: no bytes", req.id));
        let mut sim = Sim::new(stem, &[]);
        let got = sim.ask(bytes);
        let answers: Vec<_> = golden
            .frames
            .iter()
            .filter(|f| f.request.as_deref() == Some(req.id.as_str()))
            .collect();
        if answers.is_empty() {
            let first = parse_hex(&got).expect("hex")[0];
            assert!(
                first & 0x80 == 0,
                "{}: request {} was refused: {got}",
                req.id,
                hex(bytes)
            );
        }
        for resp in answers {
            let want = resp
                .corrected
                .as_deref()
                .or(resp.printed.as_deref())
                .unwrap_or_else(|| panic!("{}: no bytes", resp.id));
            assert_eq!(
                got,
                hex(want),
                "{}: request {} answered differently",
                resp.id,
                hex(bytes)
            );
            compared += 1;
        }
        replayed += 1;
    }
    assert!(replayed >= 10, "{stem}: only {replayed} requests replayed");
    assert!(compared >= 8, "{stem}: only {compared} responses compared");
}

#[test]
fn golden_replay_mdrive() {
    golden_replay("mdrive");
}

#[test]
fn golden_replay_lmd() {
    golden_replay("lmd");
}

#[test]
fn vm_write_then_read_mdrive_high_word_first() {
    let mut s = Sim::new("mdrive", &[]);
    assert_eq!(
        s.ask("03 00 8B 00 02"),
        "03 04 00 0B B8 00",
        "default 768000"
    );
    assert_eq!(s.ask("10 00 8B 00 02 04 00 09 27 C0"), "10 00 8B 00 02");
    assert_eq!(s.ask("03 00 8B 00 02"), "03 04 00 09 27 C0", "600000");
}

#[test]
fn vm_write_then_read_lmd_low_word_first() {
    let mut s = Sim::new("lmd", &[]);
    assert_eq!(
        s.ask("03 00 8B 00 02"),
        "03 04 B8 00 00 0B",
        "default 768000"
    );
    assert_eq!(s.ask("10 00 8B 00 02 04 27 C0 00 09"), "10 00 8B 00 02");
    assert_eq!(s.ask("03 00 8B 00 02"), "03 04 27 C0 00 09", "600000");
}

// ---------------------------------------------------------------------------------------------------------------
// Register map rules.
// ---------------------------------------------------------------------------------------------------------------

#[test]
fn reserved_and_unmapped_addresses_give_02() {
    run_exchanges("reserved_and_unmapped_addresses_give_02");
}

#[test]
fn read_only_write_gives_02() {
    for stem in ["mdrive", "lmd"] {
        let mut s = Sim::new(stem, &[]);
        assert_eq!(s.write16(0x004A, 1), "90 02", "{stem}: MV is read-only");
        assert_eq!(s.write16(0x001F, 1), "90 02", "{stem}: EF is read-only");
        assert_eq!(s.write32(0x0085, 5), "90 02", "{stem}: V is read-only");
    }
}

#[test]
fn out_of_range_gives_03() {
    for stem in ["mdrive", "lmd"] {
        let mut s = Sim::new(stem, &[]);
        assert_eq!(s.write32(0x0000, 90), "90 03", "{stem}: A below 91");
        assert_eq!(s.write32(0x0000, 91), "10 00 00 00 02", "{stem}: A = 91");
        assert_eq!(s.write16(0x0029, 101), "90 03", "{stem}: HC above 100");
        assert_eq!(
            s.write16(0x0048, 3),
            "90 03",
            "{stem}: MS 3 is not in the table"
        );
        assert_eq!(s.write16(0x0048, 250), "10 00 48 00 01", "{stem}: MS 250");
        assert_eq!(s.write16(0x002C, 1), "90 03", "{stem}: HT 1 is excluded");
        assert_eq!(s.write16(0x002C, 2), "10 00 2C 00 01", "{stem}: HT 2");
    }
    let mut s = Sim::new("mdrive", &[]);
    assert_eq!(s.write32(0x008B, 5_000_001), "90 03", "VM above 5000000");
    let mut s = Sim::new("lmd", &[]);
    assert_eq!(
        s.write32(0x008B, 2_560_001),
        "90 03",
        "LMD VM above 2560000"
    );
    assert_eq!(
        s.write32(0x008B, 2_560_000),
        "10 00 8B 00 02",
        "LMD VM 2560000"
    );
}

#[test]
fn vi_must_stay_below_vm() {
    for stem in ["mdrive", "lmd"] {
        let mut s = Sim::new(stem, &[]);
        assert_eq!(s.write32(0x008B, 1000), "90 03", "{stem}: VM = VI");
        assert_eq!(s.write32(0x008B, 999), "90 03", "{stem}: VM < VI");
        assert_eq!(
            s.write32(0x008B, 1001),
            "10 00 8B 00 02",
            "{stem}: VM = VI + 1"
        );
        assert_eq!(s.write32(0x0089, 1001), "90 03", "{stem}: VI = VM");
        assert_eq!(
            s.write32(0x0089, 1000),
            "10 00 89 00 02",
            "{stem}: VI = VM - 1"
        );
        assert_eq!(s.read32(0x008B), 1001);
    }
    // Above the profile's write limit of 2 (the byte count row, line 672) the request is refused (03).
    let mut s = Sim::new("mdrive", &[]);
    assert_eq!(
        s.ask("10 00 89 00 04 08 00 00 07 D0 00 00 0B B8"),
        "90 03",
        "4 registers"
    );
    // Both in one request, on a drive taking 4 registers ('Qty of addresses 1 to 4', line 671): the pair is
    // checked as written.
    let mut p = crate::support::profile("mdrive");
    for f in &mut p.functions {
        if f.code == FunctionCode::WRITE_MULTIPLE_REGISTERS {
            f.max_quantity = Some(4);
        }
    }
    let mut s = Sim::with(p, &[]);
    assert_eq!(
        s.ask("10 00 89 00 04 08 00 00 07 D0 00 00 0B B8"),
        "10 00 89 00 04",
        "VI 2000, VM 3000"
    );
    assert_eq!(
        s.ask("10 00 89 00 04 08 00 00 0B B8 00 00 07 D0"),
        "90 03",
        "VI 3000, VM 2000"
    );
    assert_eq!(s.read32(0x0089), 2000, "the refused write left VI alone");
}

#[test]
fn partial_32_bit_access() {
    let mut s = Sim::new("mdrive", &[]);
    // Reads may straddle: VI's low word and VM's high word (the manual's printed 0x008A example).
    assert_eq!(s.ask("03 00 8A 00 02"), "03 04 03 E8 00 0B");
    assert_eq!(s.ask("03 00 8C 00 01"), "03 02 B8 00");
    // Writes must cover whole registers.
    assert_eq!(
        s.ask("10 00 8C 00 01 02 00 01"),
        "90 02",
        "VM's low word alone"
    );
    assert_eq!(
        s.ask("10 00 8A 00 02 04 00 01 00 0B"),
        "90 02",
        "VI low + VM high"
    );
    assert_eq!(s.read32(0x008B), 768_000);
}

// ---------------------------------------------------------------------------------------------------------------
// Motion over virtual time.
// ---------------------------------------------------------------------------------------------------------------

fn flags(s: &mut Sim) -> (u16, u16, u16) {
    (s.read16(0x004A), s.read16(0x0088), s.read16(0x0045))
}

#[test]
fn relative_move_reaches_target_over_time() {
    for stem in ["mdrive", "lmd"] {
        let mut s = Sim::new(stem, &[]);
        s.at_ms(1000);
        assert_eq!(s.read32(0x0057), 0, "{stem}: P at t0");
        assert_eq!(flags(&mut s), (0, 0, 0), "{stem}: idle");
        assert_eq!(
            s.write32(0x0046, 10_000),
            "10 00 46 00 02",
            "{stem}: MR 10000"
        );
        // Defaults VI 1000, VM 768000, A = D = 1e6: a triangle peaking near 100005 steps/s, ~198 ms long.
        assert_eq!(s.read32(0x0057), 0, "{stem}: P right at the start");
        s.at_ms(1010);
        assert_eq!(
            flags(&mut s),
            (1, 1, 1),
            "{stem}: moving, accelerating, to position"
        );
        let early = s.read32(0x0057);
        s.at_ms(1100);
        let mid = s.read32(0x0057);
        let v = s.read32(0x0085);
        assert!(
            0 < early && early < mid && mid < 10_000,
            "{stem}: {early} {mid}"
        );
        assert!(v > 1000, "{stem}: velocity {v}");
        assert_eq!(s.read32(0x0005), mid, "{stem}: C1 counts the same steps");
        s.at_ms(1150);
        let late = s.read32(0x0057);
        assert!(mid < late && late < 10_000, "{stem}: {mid} {late}");
        s.at_ms(1195);
        assert_eq!(
            flags(&mut s).0,
            1,
            "{stem}: still moving at 195 ms (the move takes 198 ms)"
        );
        s.at_ms(1199);
        assert_eq!(flags(&mut s).0, 0, "{stem}: done at 199 ms");
        s.at_ms(2000);
        assert_eq!(s.read32(0x0057), 10_000, "{stem}: P at the end");
        assert_eq!(s.read32(0x0005), 10_000, "{stem}: C1 at the end");
        assert_eq!(s.read32(0x0085), 0, "{stem}: stopped");
        assert_eq!(flags(&mut s), (0, 0, 0), "{stem}: flags cleared");
        // Absolute move back past zero.
        assert_eq!(
            s.write32(0x0043, -5_000),
            "10 00 43 00 02",
            "{stem}: MA -5000"
        );
        s.at_ms(2010);
        assert_eq!(flags(&mut s).0, 1);
        let p = s.read32(0x0057);
        assert!(p < 10_000 && p > -5_000, "{stem}: {p}");
        s.at_ms(5000);
        assert_eq!(s.read32(0x0057), -5_000, "{stem}: MA target");
        assert_eq!(flags(&mut s), (0, 0, 0));
    }
}

#[test]
fn long_move_cruises_at_vm() {
    let mut s = Sim::new("mdrive", &[]);
    s.write32(0x008B, 100_000);
    s.write32(0x0046, 1_000_000);
    // Accelerates to 100000 in 99 ms, cruises ~9.9 s, decelerates in 99 ms.
    s.at_ms(5000);
    assert_eq!(s.read32(0x0085), 100_000, "cruising at VM");
    assert_eq!(flags(&mut s), (1, 0, 1), "moving, constant velocity");
    s.at_ms(11_000);
    assert_eq!(s.read32(0x0057), 1_000_000);
    assert_eq!(flags(&mut s), (0, 0, 0));
}

#[test]
fn slew_runs_until_stopped() {
    let mut s = Sim::new("mdrive", &[]);
    assert_eq!(s.write32(0x0078, -20_000), "10 00 78 00 02", "SL -20000");
    s.at_ms(1000);
    assert_eq!(s.read32(0x0085), -20_000);
    assert_eq!(
        flags(&mut s),
        (1, 0, 0),
        "slewing: moving, not to a position"
    );
    let p1 = s.read32(0x0057);
    s.at_ms(2000);
    let p2 = s.read32(0x0057);
    assert_eq!(p1 - p2, 20_000, "one second at 20000 steps/s");
    assert_eq!(s.write32(0x0078, 0), "10 00 78 00 02", "SL 0");
    s.at_ms(2005);
    assert_eq!(flags(&mut s).1, 1, "decelerating");
    s.at_ms(3000);
    assert_eq!(flags(&mut s), (0, 0, 0));
    let stop = s.read32(0x0057);
    s.at_ms(4000);
    assert_eq!(s.read32(0x0057), stop, "stays put");
    assert!(stop < p2 && stop > p2 - 1000, "{stop} after {p2}");
}

#[test]
fn move_refused_while_moving_or_disabled() {
    let mut s = Sim::new("mdrive", &[]);
    s.write32(0x0046, 100_000);
    s.at_ms(10);
    assert_eq!(s.write32(0x0046, 5), "90 04", "MR during a move");
    assert_eq!(s.write32(0x0043, 5), "90 04", "MA during a move");
    // DE = 0 stops the axis where it is.
    assert_eq!(s.write16(0x001C, 0), "10 00 1C 00 01");
    assert_eq!(flags(&mut s), (0, 0, 0));
    let p = s.read32(0x0057);
    assert!(p > 0 && p < 100_000, "{p}");
    s.at_ms(5000);
    assert_eq!(s.read32(0x0057), p, "no motion while disabled");
    assert_eq!(s.write32(0x0046, 5), "90 04", "MR while disabled");
    assert_eq!(s.write16(0x001C, 1), "10 00 1C 00 01");
    assert_eq!(s.write32(0x0046, 5), "10 00 46 00 02", "MR once enabled");
    s.at_ms(6000);
    assert_eq!(s.read32(0x0057), p + 5);
}

#[test]
fn writing_p_sets_the_reference_without_moving() {
    let mut s = Sim::new("lmd", &[]);
    assert_eq!(s.write32(0x0057, 123_456), "10 00 57 00 02");
    assert_eq!(flags(&mut s), (0, 0, 0));
    assert_eq!(s.read32(0x0057), 123_456);
    assert_eq!(s.read32(0x0005), 0, "C1 is a counter of its own");
    s.write32(0x0043, 123_000);
    s.at_ms(10_000);
    assert_eq!(s.read32(0x0057), 123_000);
    assert_eq!(s.read32(0x0005), -456);
}

#[test]
fn save_is_recorded() {
    let mut m = Mdrive::new(
        profile("mdrive"),
        FaultSet::none(),
        drives::Choices::reference(),
    );
    let r = m.handle(
        Duration::ZERO,
        1,
        &Request::WriteMultipleRegisters {
            address: 0x0076,
            values: vec![1],
        },
    );
    assert_eq!(
        r,
        Some(Response::WriteMultipleRegisters {
            address: 0x0076,
            quantity: 1
        })
    );
    assert_eq!(m.nvm_writes(), 1);
    assert_eq!(
        m.handle(
            Duration::ZERO,
            1,
            &Request::ReadHoldingRegisters {
                address: 0x0076,
                quantity: 1
            }
        ),
        Some(Response::exception(
            FunctionCode::READ_HOLDING_REGISTERS,
            ExceptionCode::ILLEGAL_DATA_ADDRESS
        )),
        "Save is write-only"
    );
}

// ---------------------------------------------------------------------------------------------------------------
// I/O.
// ---------------------------------------------------------------------------------------------------------------

#[test]
fn io_coils_inputs_and_their_registers() {
    let mut s = Sim::new("mdrive", &[]);
    assert_eq!(s.ask("02 00 2D 00 04"), "02 01 0B");
    assert_eq!(s.read16(0x003B), 0x0B, "IN");
    assert_eq!(s.read16(0x002F), 0, "I3");
    assert_eq!(s.ask("02 00 2E 00 04"), "82 02", "input 5 does not exist");
    assert_eq!(s.ask("01 00 4B 00 04"), "01 01 05");
    assert_eq!(s.ask("05 00 4C FF 00"), "05 00 4C FF 00", "output 2 on");
    assert_eq!(s.ask("01 00 4B 00 04"), "01 01 07");
    assert_eq!(s.read16(0x004C), 1, "O2");
    assert_eq!(s.read16(0x0056), 7, "OT");
    assert_eq!(s.write16(0x0056, 8), "10 00 56 00 01", "OT = output 4 only");
    assert_eq!(s.ask("01 00 4B 00 04"), "01 01 08");
    assert_eq!(s.write16(0x004B, 1), "10 00 4B 00 01", "O1 on");
    assert_eq!(s.ask("01 00 4B 00 02"), "01 01 01");
    assert_eq!(s.ask("05 00 4F FF 00"), "85 02", "no output 5");
    assert_eq!(s.ask("05 00 4B 12 34"), "85 03", "illegal coil value");
    assert_eq!(s.write16(0x002D, 0), "90 02", "inputs are read-only");

    // The reference LMD has output 4 (coil 0x0003, freedom `lmd-output-4` = present): no register O4, OT bit 3.
    let mut s = Sim::new("lmd", &[]);
    assert_eq!(s.ask("01 00 00 00 04"), "01 01 05", "the LMD's outputs 1-4");
    assert_eq!(s.ask("01 00 04 00 01"), "81 02", "no output 5");
    assert_eq!(s.ask("01 00 00 00 03"), "01 01 05");
    assert_eq!(s.ask("02 00 00 00 04"), "02 01 0B");
    assert_eq!(s.ask("05 00 01 FF 00"), "05 00 01 FF 00");
    assert_eq!(s.read16(0x004C), 1, "LMD O2");
    assert_eq!(s.read16(0x0056), 7, "LMD OT");
    assert_eq!(s.ask("05 00 03 FF 00"), "05 00 03 FF 00", "output 4 on");
    assert_eq!(s.read16(0x0056), 15, "LMD OT with output 4");

    // An LMD with three outputs (`lmd-output-4=exception-02`) refuses whatever covers coil 0x0003, alone.
    s.station = chosen_station("lmd", &["lmd-output-4=exception-02"]);
    assert_eq!(s.ask("01 00 00 00 04"), "81 02", "a 3-output LMD");
    assert_eq!(s.ask("01 00 03 00 01"), "81 02");
    assert_eq!(s.ask("05 00 03 FF 00"), "85 02");
    assert_eq!(
        s.ask("0F 00 02 00 02 01 01"),
        "8F 01",
        "no FC 0F on the LMD: 01 first"
    );
    assert_eq!(s.ask("01 00 00 00 03"), "01 01 05", "outputs 1-3 served");
    assert_eq!(s.ask("05 00 02 00 00"), "05 00 02 00 00");
}

#[test]
fn inputs_follow_the_outside_world() {
    let mut m = Mdrive::new(
        profile("mdrive"),
        FaultSet::none(),
        drives::Choices::reference(),
    );
    assert!(m.set_input(3, true));
    assert!(!m.set_input(5, true));
    let r = m.handle(
        Duration::ZERO,
        1,
        &Request::ReadDiscreteInputs {
            address: 0x002D,
            quantity: 4,
        },
    );
    assert_eq!(r, Some(Response::ReadDiscreteInputs { data: vec![0x0F] }));
    assert_eq!(m.bank().value(0x003B), Some(15), "IN");
}

// ---------------------------------------------------------------------------------------------------------------
// Vendor mnemonics (FC 0x41 / 0x42).
// ---------------------------------------------------------------------------------------------------------------

#[test]
fn vendor_mnemonics_round_trip() {
    let mut s = Sim::new("mdrive", &[]);
    assert_eq!(
        s.vendor_read("S1").as_deref(),
        Ok("0, 0, 0"),
        "default (line 1263)"
    );
    assert_eq!(s.vendor_write("S1", "=0,1,0"), "42 04 20 20 31 53");
    assert_eq!(s.vendor_read("S1").as_deref(), Ok("0, 1, 0"));
    assert_eq!(s.vendor_write("S1", "=17"), "42 04 20 20 31 53", "only A");
    assert_eq!(s.vendor_read("S1").as_deref(), Ok("17, 1, 0"));
    assert_eq!(s.vendor_read("TR").as_deref(), Ok("0, 0, 0"));
    assert_eq!(s.vendor_write("TR", "=6500"), "42 04 20 20 52 54");
    assert_eq!(s.vendor_read("TR").as_deref(), Ok("6500, 0, 0"));
    assert_eq!(s.vendor_write("CR", "=1.500"), "42 04 20 20 52 43");
    assert_eq!(s.vendor_read("CR").as_deref(), Ok("1.500"));
    assert_eq!(s.vendor_write("S13", "=61,1"), "42 04 20 33 31 53");
    assert_eq!(s.vendor_read("S13").as_deref(), Ok("61, 1"));
    // MU mirrors register 0x00A0 both ways.
    assert_eq!(s.vendor_read("MU").as_deref(), Ok("0, 0"));
    assert_eq!(s.vendor_write("MU", "=2,1"), "42 04 20 20 55 4D");
    assert_eq!(s.read16(0x00A0), 2);
    assert_eq!(s.write16(0x00A0, 1), "10 00 A0 00 01");
    assert_eq!(s.vendor_read("MU").as_deref(), Ok("1, 1"));
    // Program commands.
    assert_eq!(s.vendor_write("EX", "A3"), "42 04 20 20 58 45");
    assert_eq!(s.vendor_write("PS", ""), "42 04 20 20 53 50");
    assert_eq!(s.vendor_write("E", ""), "42 04 20 20 20 45");
}

#[test]
fn vendor_errors() {
    let mut s = Sim::new("mdrive", &[]);
    assert_eq!(s.vendor_read("ZZ"), Err("C1 02".into()), "unknown mnemonic");
    assert_eq!(s.vendor_write("ZZ", "=1"), "C2 02");
    assert_eq!(s.vendor_read("E"), Err("C1 02".into()), "E is write-only");
    assert_eq!(s.vendor_write("E", "1"), "C2 03", "E takes no parameters");
    assert_eq!(s.vendor_write("EX", ""), "C2 03", "EX needs a label");
    assert_eq!(
        s.vendor_write("S5", "=0,0"),
        "C2 03",
        "mode 0 is not in the table"
    );
    assert_eq!(
        s.vendor_write("S13", "=0,0"),
        "C2 03",
        "the printed hex of S13"
    );
    assert_eq!(s.vendor_write("S1", "0,1,0"), "C2 03", "no '='");
    assert_eq!(s.vendor_write("S1", "=0,1,0,1"), "C2 03", "4 values");
    assert_eq!(s.vendor_write("S1", "=4,0,0"), "C2 03", "type 4 undefined");
    assert_eq!(s.vendor_write("S1", "=a,0,0"), "C2 03", "not a number");
    assert_eq!(s.vendor_write("S1", "=0,,0"), "C2 03", "empty value");
    assert_eq!(
        s.vendor_write("TR", &format!("={}", "1".repeat(28))),
        "C2 03",
        "29 bytes"
    );
    assert_eq!(
        s.ask("42 20 20 31 53 06 3D 30 2C 31 2C 07"),
        "C2 03",
        "control character"
    );
    assert_eq!(
        s.vendor_read("S1").as_deref(),
        Ok("0, 0, 0"),
        "nothing stuck"
    );
    // A mnemonic in the wrong byte order is another (unknown) mnemonic.
    assert_eq!(s.ask("41 53 31 20 20"), "C1 02");

    let mut s = Sim::new("lmd", &[]);
    assert_eq!(s.vendor_read("IT").as_deref(), Ok("52,37"));
    assert_eq!(s.vendor_read("VT").as_deref(), Ok("22,37"));
    assert_eq!(s.vendor_write("IT", "=1"), "C2 02", "IT is read-only");
    assert_eq!(s.vendor_write("IS", "=0,0,0"), "C2 03", "line 0");
    assert_eq!(
        s.vendor_write("IS", "=5,0,0"),
        "C2 03",
        "analog line, mode 0"
    );
    assert_eq!(s.vendor_write("IS", "=2,12,1"), "42 04 20 20 53 49");
    assert_eq!(s.vendor_write("OS", "=0,0,0"), "C2 03");
    assert_eq!(
        s.vendor_write("OS", "=1,28,0"),
        "C2 03",
        "trip on output 3 only"
    );
    assert_eq!(s.vendor_write("OS", "=3,28,0"), "42 04 20 20 53 4F");
    assert_eq!(s.vendor_read("OS").as_deref(), Ok("3, 28, 0"));
    assert_eq!(s.vendor_write("AO", "=65536"), "C2 03");
}

#[test]
fn program_commands_are_recorded() {
    let mut m = Mdrive::new(
        profile("lmd"),
        FaultSet::none(),
        drives::Choices::reference(),
    );
    let w = |name: &str, p: &str| Request::VendorWrite {
        mnemonic: Mnemonic::from_name(name).expect("mnemonic"),
        params: p.as_bytes().to_vec(),
    };
    m.handle(Duration::ZERO, 1, &w("EX", " G1"));
    assert_eq!(m.program(), &Program::Running("G1".into()));
    m.handle(Duration::ZERO, 1, &w("PS", ""));
    assert_eq!(m.program(), &Program::Paused("G1".into()));
    m.handle(Duration::ZERO, 1, &w("RS", ""));
    assert_eq!(m.program(), &Program::Running("G1".into()));
    m.handle(Duration::ZERO, 1, &w("\u{1b}", ""));
    assert_eq!(m.program(), &Program::Idle);
}

// ---------------------------------------------------------------------------------------------------------------
// Device identification.
// ---------------------------------------------------------------------------------------------------------------

#[test]
fn device_identification() {
    let mut s = Sim::new("mdrive", &[]);
    let basic = format!(
        "2B 0E 01 82 00 00 03 00 07 {} 01 0A {} 02 07 {}",
        ascii_hex("SEM USA"),
        ascii_hex("MDrive P/N"),
        ascii_hex("4.0.0.0")
    );
    assert_eq!(s.ask("2B 0E 01 00"), basic, "basic stream");
    assert_eq!(
        s.ask("2B 0E 01 05"),
        basic,
        "object 5 is not basic: restart at 0"
    );
    assert_eq!(s.ask("2B 0E 01 09"), basic, "unknown object: restart at 0");
    assert_eq!(
        s.ask("2B 0E 02 05"),
        format!(
            "2B 0E 02 82 00 00 02 05 0D {} 06 0B {}",
            ascii_hex("Serial number"),
            ascii_hex("ASI 4.x.x.x")
        ),
        "regular stream from object 5"
    );
    assert_eq!(
        s.ask("2B 0E 04 03"),
        format!(
            "2B 0E 04 82 00 00 01 03 0F {}",
            ascii_hex("www.imshome.com")
        ),
        "individual"
    );
    assert_eq!(s.ask("2B 0E 04 07"), "AB 02", "individual, unknown object");
    assert_eq!(s.ask("2B 0E 05 00"), "AB 03", "bad read code");
    assert_eq!(s.ask("2B 0E 00 00"), "AB 03", "bad read code 0");
    let regular = s.ask("2B 0E 02 00");
    let extended = s.ask("2B 0E 03 00");
    assert_eq!(
        extended,
        regular.replacen("2B 0E 02", "2B 0E 03", 1),
        "an extended read of a regular device answers at its level"
    );
    assert_eq!(
        s.ask("2B 0D 00 00 01 00 29 00 00 00 00 02"),
        "AB 01",
        "MEI 0x0D"
    );
}

// ---------------------------------------------------------------------------------------------------------------
// Each model-level fault makes the drive answer differently from the healthy one.
// ---------------------------------------------------------------------------------------------------------------

#[test]
fn fault_word_order() {
    assert_fault_shows(
        &profile("mdrive"),
        Fault::WordOrder,
        &["03 00 8B 00 02"],
        &["03 04 00 0B B8 00"],
        &["03 04 B8 00 00 0B"],
    );
    // Writes too: the high-first write of 600000 lands as 0x27C00009 (out of range) on the faulted drive.
    assert_fault_shows(
        &profile("mdrive"),
        Fault::WordOrder,
        &["10 00 8B 00 02 04 00 09 27 C0"],
        &["10 00 8B 00 02"],
        &["90 03"],
    );
    assert_fault_shows(
        &profile("lmd"),
        Fault::WordOrder,
        &["03 00 8B 00 02"],
        &["03 04 B8 00 00 0B"],
        &["03 04 00 0B B8 00"],
    );
}

#[test]
fn fault_reserved_readable() {
    assert_fault_shows(
        &profile("mdrive"),
        Fault::ReservedReadable,
        &[
            "03 00 02 00 01",
            "03 00 C0 00 02",
            "10 00 02 00 01 02 00 01",
        ],
        &["83 02", "83 02", "90 02"],
        &["03 02 00 00", "03 04 00 00 00 00", "90 02"],
    );
}

#[test]
fn fault_read_only_writable() {
    assert_fault_shows(
        &profile("mdrive"),
        Fault::ReadOnlyWritable,
        &["10 00 1F 00 01 02 00 01", "03 00 1F 00 01"],
        &["90 02", "03 02 00 00"],
        &["10 00 1F 00 01", "03 02 00 01"],
    );
    let mut ok = Sim::new("lmd", &[]);
    let mut bad = Sim::new("lmd", &[Fault::ReadOnlyWritable]);
    assert_eq!(ok.vendor_write("IT", "=9,9"), "C2 02");
    assert_eq!(bad.vendor_write("IT", "=9,9"), "42 04 20 20 54 49");
    assert_eq!(bad.vendor_read("IT").as_deref(), Ok("9, 9"));
}

#[test]
fn fault_range_unchecked() {
    let (ok, bad) = both(
        &profile("mdrive"),
        Fault::RangeUnchecked,
        &[
            "10 00 00 00 02 04 00 00 00 5A",
            "10 00 8B 00 02 04 00 00 01 F4",
            "42 20 20 35 53 04 3D 30 2C 30",
        ],
    );
    assert_eq!(
        ok,
        ["90 03", "90 03", "C2 03"],
        "A 90; VM 500 < VI; S5 =0,0"
    );
    assert_eq!(
        bad,
        ["10 00 00 00 02", "10 00 8B 00 02", "42 04 20 20 35 53"]
    );
}

#[test]
fn fault_quantity_unchecked() {
    let (ok, bad) = both(
        &profile("mdrive"),
        Fault::QuantityUnchecked,
        &["03 00 A5 00 05", "03 00 A5 00 00", "01 00 4B 00 05"],
    );
    assert_eq!(ok, ["83 03", "83 03", "81 03"]);
    assert_eq!(
        bad,
        ["03 0A 00 01 00 19 00 00 00 00 00 00", "03 00", "81 02"]
    );
}

#[test]
fn fault_quantity_low_byte() {
    // Quantity 0x0101 registers and 0x0801 coils: above every limit, the low byte (1) within the MDrive's.
    let (ok, bad) = both(
        &profile("mdrive"),
        Fault::QuantityLowByte,
        &["03 00 A5 01 01", "01 00 4B 08 01", "03 00 A5 00 05"],
    );
    assert_eq!(ok, ["83 03", "81 03", "83 03"]);
    assert_eq!(bad[2], "83 03", "a quantity below 256 is read whole");
    assert!(bad[0].starts_with("03 02 "), "{bad:?}");
    assert!(bad[1].starts_with("01 01 "), "{bad:?}");
}

#[test]
fn fault_quantity_over_spec_dropped() {
    let mut st = Sim::with(profile("mdrive"), &[Fault::QuantityOverSpecDropped]);
    // The device's own limit is still answered; the specification's is not.
    assert_eq!(st.ask("03 00 A5 00 05"), "83 03");
    let mut adu = Vec::new();
    codec::tcp::encode_adu(9, 1, &parse_hex("03 00 A5 00 7E").expect("hex"), &mut adu)
        .expect("encodes");
    assert!(st.station.tcp_adu(Duration::ZERO, &adu).is_none());
}

// ---------------------------------------------------------------------------------------------------------------
// No request makes the station panic, and every answer decodes strictly.
// ---------------------------------------------------------------------------------------------------------------

/// Function codes the drives implement, plus neighbours.
const FCS: &[u8] = &[
    0x01, 0x02, 0x03, 0x04, 0x05, 0x06, 0x08, 0x0F, 0x10, 0x17, 0x2B, 0x41, 0x42, 0xC1,
];

/// A PDU: fully random, or a plausible function code + address in the map + small quantity + random tail,
/// or a vendor request with a known mnemonic.
fn pdu() -> impl Strategy<Value = Vec<u8>> {
    let names = vec![
        "S1", "S5", "S13", "TR", "MU", "E", "EX", "IS", "OS", "IT", "AO", "CR", "\u{1b}", "ZZ",
    ];
    prop_oneof![
        vec(any::<u8>(), 0..=260),
        (select(FCS), 0u16..0xC0, 0u16..8, vec(any::<u8>(), 0..12)).prop_map(|(fc, a, q, tail)| {
            let mut p = vec![fc];
            p.extend_from_slice(&a.to_be_bytes());
            p.extend_from_slice(&q.to_be_bytes());
            p.extend(tail);
            p
        }),
        (
            select(vec![0x41u8, 0x42]),
            select(names),
            "[=0-9,. A-Za-z-]{0,30}"
        )
            .prop_map(|(fc, name, params)| {
                let mut p = vec![fc];
                p.extend_from_slice(&Mnemonic::from_name(name).map(|m| m.0).unwrap_or([0; 4]));
                if fc == 0x42 {
                    p.push(params.len() as u8);
                    p.extend_from_slice(params.as_bytes());
                }
                p
            }),
    ]
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(256))]
    #[test]
    fn random_requests_never_panic_and_answers_decode(
        lmd in any::<bool>(),
        faults in subsequence(MODEL_FAULTS.to_vec(), 0..=MODEL_FAULTS.len()),
        steps in vec((pdu(), 0u64..500), 1..12),
    ) {
        let mut s = Sim::new(if lmd { "lmd" } else { "mdrive" }, &faults);
        let mut now = Duration::ZERO;
        for (i, (pdu, dt)) in steps.iter().enumerate() {
            now += Duration::from_millis(*dt);
            s.answer_decodes(i, now, pdu)?;
        }
    }
}

/// `partial-register-write=response`: a write of the low word of A (0x0000-0x0001, high word first) is
/// taken, and the high word kept; the reference refuses it with 02.
#[test]
fn a_drive_taking_half_a_register_stores_that_half() {
    let mut reference = Sim::new("mdrive", &[]);
    assert_eq!(reference.ask("10 00 01 00 01 02 12 34"), "90 02");
    assert_eq!(reference.ask("03 00 00 00 02"), "03 04 00 0F 42 40");
    let mut s = Sim::new("mdrive", &[]);
    s.station = chosen_station("mdrive", &["partial-register-write=response"]);
    assert_eq!(s.ask("10 00 01 00 01 02 12 34"), "10 00 01 00 01");
    assert_eq!(
        s.ask("03 00 00 00 02"),
        "03 04 00 0F 12 34",
        "low word taken"
    );
    // The value range still holds for the value the half makes: 0x7FFF_4240 is above A's maximum.
    assert_eq!(s.ask("10 00 00 00 01 02 7F FF"), "90 03");
}

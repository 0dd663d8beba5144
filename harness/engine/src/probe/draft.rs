//! `probe --write-profile`: a draft profile from what a probe read. Every entry is marked
//! `confirmed = false` and claims only what the reads showed: a register entry has no `width` or `access`
//! (reads show 16-bit words that answer, not which pairs form a 32-bit value nor what a write would do),
//! no range and no default; function codes the probe did not send are neither listed nor called
//! unsupported. The `[draft]` table records what was probed, so the catalog judges only that.

use std::fmt::Write;

use super::{ProbeReport, Support, id_object_name};
use crate::cases::catalog::slug_of_length;
use crate::targets::TargetUrl;
use codec::{Framing, Parity};

/// A TOML string literal (quoted and escaped).
fn q(s: &str) -> String {
    toml::Value::String(s.to_string()).to_string()
}

/// A name as an id: lowercase ASCII letters and digits, dashes between, at most 40 characters.
fn slug(s: &str) -> String {
    slug_of_length(s, 40)
}

/// The unit ids to claim: the range that agrees with every unit id probed, if there is one.
fn unit_range(unit: u8, probed: &[(u8, bool)]) -> Option<(u8, u8)> {
    let answered = probed.iter().filter(|(_, a)| *a).map(|(u, _)| *u);
    let lo = answered.clone().chain([unit]).min()?;
    let hi = answered.chain([unit]).max()?;
    probed
        .iter()
        .all(|(u, a)| *a == (lo..=hi).contains(u))
        .then_some((lo, hi))
}

/// The draft profile text of a probe of `url` at `unit` over `scan`.
pub fn write(report: &ProbeReport, url: &TargetUrl, unit: u8, scan: (u16, u16)) -> String {
    let mut s = String::new();
    let object = |id: u8| {
        report
            .identification
            .iter()
            .find(|(i, _)| *i == id)
            .map(|(_, v)| String::from_utf8_lossy(v).trim().to_string())
            .filter(|v| !v.is_empty())
    };
    let product = object(0x01).or_else(|| object(0x04));
    let id = match product.as_deref().map(slug).filter(|s| !s.is_empty()) {
        Some(p) => format!("{p}-draft"),
        None => "drive-draft".to_string(),
    };
    let name = object(0x04)
        .or_else(|| object(0x01))
        .unwrap_or_else(|| format!("Drive at {url}"));
    let vendor = object(0x00).unwrap_or_else(|| "unknown".into());
    let framing = report.framing.unwrap_or(Framing::Tcp);
    let transport = if framing == Framing::Rtu {
        "rtu"
    } else {
        "tcp"
    };

    let _ = writeln!(
        s,
        "# Draft profile written by `modbus-harness probe --write-profile` from {url} (unit {unit}),\n\
# with read requests only{}. Every entry below is marked `confirmed = false`: the harness only reads\n\
# unconfirmed entries (no write, out-of-range or read-only cases). Reads cannot show a register's width,\n\
# range or access, so the entries have none: confirm each one (width, access, min/max, default, motion,\n\
# destructive), then delete its `confirmed = false`. Delete [draft] once the function list and the map are\n\
# complete. The format: corpus/profiles/SCHEMA.md; the steps: README.md, \"Test your own drive\".\n",
        if report.write_requests > 0 {
            " (and, with --probe-writes, write function codes in requests a drive must reject)"
        } else {
            ""
        }
    );
    let _ = writeln!(s, "[device]");
    let _ = writeln!(s, "id = {}", q(&id));
    let _ = writeln!(s, "name = {}", q(&name));
    let _ = writeln!(s, "vendor = {}", q(&vendor));
    let _ = writeln!(s, "transports = [{}]", q(transport));
    let _ = writeln!(s, "default_unit = {unit}");
    if framing == Framing::Tcp && !report.units.is_empty() {
        let list = |a: bool| {
            let mut v: Vec<u8> = report
                .units
                .iter()
                .filter(|(_, x)| *x == a)
                .map(|(u, _)| *u)
                .chain(a.then_some(unit))
                .collect();
            v.sort_unstable();
            match v.is_empty() {
                true => "none".to_string(),
                false => v.iter().map(u8::to_string).collect::<Vec<_>>().join(", "),
            }
        };
        let seen = format!(
            "reads answered at unit ids {}; not at {}",
            list(true),
            list(false)
        );
        match unit_range(unit, &report.units) {
            Some((lo, hi)) => {
                let _ = writeln!(s, "unit_ids = [{lo}, {hi}]  # {seen}");
            }
            None => {
                let _ = writeln!(
                    s,
                    "unit_ids = [{unit}, {unit}]  # {seen}: no range fits them, the tcp/unit-id cases will show it"
                );
            }
        }
    } else {
        let _ = writeln!(
            s,
            "unit_ids = [{unit}, {unit}]  # other unit ids not probed{}",
            if framing == Framing::Rtu {
                " (on a serial line they are other drives)"
            } else {
                ""
            }
        );
    }
    let _ = writeln!(
        s,
        "note = {}",
        q(&format!(
            "Drafted by modbus-harness probe from {url}. Not discovered: word_order (high-first assumed), max_pdu (253), \
the quantity limits (the spec's), broadcast (false), which registers form 32-bit values, access and ranges."
        ))
    );
    if let TargetUrl::Serial { baud, format, .. } = url {
        let parity = match format.parity {
            Parity::None => "none",
            Parity::Even => "even",
            Parity::Odd => "odd",
        };
        let _ = writeln!(s, "\n[serial]  # the line settings the probe used");
        let _ = writeln!(s, "baud_rates = [{baud}]");
        let _ = writeln!(s, "default_baud = {baud}");
        let _ = writeln!(s, "parity = [{}]", q(parity));
        let _ = writeln!(s, "default_parity = {}", q(parity));
        let _ = writeln!(s, "stop_bits = {}", format.stop_bits);
    }

    // The function codes whose support is `which`, as hex.
    let functions = |which: fn(&Support) -> bool| -> Vec<String> {
        report
            .functions
            .iter()
            .filter(|(_, sup)| which(sup))
            .map(|(fc, _)| format!("0x{fc:02X}"))
            .collect()
    };
    let unsupported = functions(|sup| *sup == Support::No);
    let _ = writeln!(s, "\n[draft]");
    let _ = writeln!(s, "target = {}", q(&url.to_string()));
    let _ = writeln!(
        s,
        "scan = [0x{:04X}, 0x{:04X}]  # addresses read one by one (registers, coils, discrete inputs)",
        scan.0, scan.1
    );
    let _ = writeln!(
        s,
        "unsupported_functions = [{}]  # answered exception 01",
        unsupported.join(", ")
    );
    let silent = functions(|sup| *sup == Support::Silent);
    let not_probed = functions(|sup| matches!(sup, Support::NotProbed(_)));
    // FC 11 is answered with a server id whose length only the device's documentation gives: a profile that
    // lists it needs a [server_id] table the probe cannot write, so it is named here instead.
    let server_id_answered = report
        .functions
        .iter()
        .any(|(fc, sup)| *fc == 0x11 && matches!(sup, Support::Yes(_)));
    let _ = writeln!(
        s,
        "note = {}",
        q(&format!(
            "Not answered: [{}]. Not probed: [{}]. Neither is listed as supported or unsupported.{}",
            silent.join(", "),
            not_probed.join(", "),
            if server_id_answered {
                " FC 0x11 (Report Server ID) was answered but is not listed: list it with a [server_id] table \
                 (the id, its length and the additional data are device specific, spec 6.13)."
            } else {
                ""
            }
        ))
    );

    for (fc, sup) in &report.functions {
        let Support::Yes(how) = sup else { continue };
        if *fc == 0x11 {
            continue;
        }
        let name = codec::FunctionCode(*fc).name().unwrap_or("Function");
        let _ = writeln!(s, "\n[[function]]");
        let _ = writeln!(s, "code = 0x{fc:02X}");
        let _ = writeln!(s, "name = {}", q(name));
        let _ = writeln!(s, "confirmed = false");
        let _ = writeln!(s, "note = {}", q(&format!("probe: {how}")));
    }
    if report.echo {
        let _ = writeln!(s, "\n[[diagnostic]]");
        let _ = writeln!(s, "sub_function = 0x00");
        let _ = writeln!(s, "name = \"Return Query Data\"");
        let _ = writeln!(s, "counter = \"echo\"");
        let _ = writeln!(s, "confirmed = false");
    }

    for (table, label, ranges) in [
        ("holding", "Holding register", &report.holding),
        ("input", "Input register", &report.input),
    ] {
        for (a, b) in ranges {
            let fc = if table == "holding" { "03" } else { "04" };
            if a == b {
                let _ = writeln!(
                    s,
                    "\n[[register]]  # FC {fc} reads one register at 0x{a:04X}"
                );
            } else {
                let _ = writeln!(
                    s,
                    "\n[[register]]  # FC {fc} reads one register at each address 0x{a:04X}-0x{b:04X}"
                );
            }
            let _ = writeln!(s, "address = 0x{a:04X}");
            if b > a {
                let _ = writeln!(s, "count = {}", u32::from(*b) - u32::from(*a) + 1);
            }
            let _ = writeln!(s, "name = {}", q(&format!("{label} {{address}}")));
            let _ = writeln!(s, "table = {}", q(table));
            let _ = writeln!(s, "confirmed = false");
        }
    }
    for (kind, label, ranges) in [
        ("coil", "Coil", &report.coils),
        ("discrete_input", "Discrete input", &report.discrete_inputs),
    ] {
        for (a, b) in ranges {
            let _ = writeln!(s, "\n[[{kind}]]");
            let _ = writeln!(s, "address = {a}");
            if b > a {
                let _ = writeln!(s, "count = {}", u32::from(*b) - u32::from(*a) + 1);
            }
            let _ = writeln!(s, "name = {}", q(&format!("{label} {{address}}")));
            let _ = writeln!(s, "confirmed = false");
        }
    }
    for (oid, v) in &report.identification {
        let _ = writeln!(s, "\n[[identification]]");
        let _ = writeln!(s, "object_id = 0x{oid:02X}");
        let _ = writeln!(s, "name = {}", q(&id_object_name(*oid)));
        let _ = writeln!(s, "value = {}", q(&String::from_utf8_lossy(v)));
        let _ = writeln!(s, "confirmed = false");
    }
    s
}

#[cfg(test)]
mod tests {
    use super::unit_range;

    #[test]
    fn the_unit_range_agrees_with_every_probe_or_is_not_claimed() {
        let all = [(0, true), (247, true), (255, true)];
        assert_eq!(unit_range(1, &all), Some((0, 255)));
        let none = [(0, false), (247, false), (255, false)];
        assert_eq!(unit_range(1, &none), Some((1, 1)));
        // 1..=247 answered but 255 not: a range fits.
        assert_eq!(
            unit_range(1, &[(0, false), (247, true), (255, false)]),
            Some((1, 247))
        );
        // 0 and 255 answered but 247 not: no range fits.
        assert_eq!(unit_range(1, &[(0, true), (247, false), (255, true)]), None);
    }
}

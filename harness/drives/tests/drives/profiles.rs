//! Profile files: blocks (`count`/`end`, `stride`, name templates) expand to the entries written out one by one,
//! the generic profile written with blocks loads to exactly the profile it was before, unconfirmed (probed)
//! entries, and every validation error names the file, the line and the reason.

use drives::corpus::Corpus;
use drives::profile::{Access, Profile, ProfileError, Table};

/// A minimal valid `[device]` table; the tests append the entries under test.
const DEVICE: &str = r#"[device]
id = "t"
name = "Test drive"
vendor = "nobody"
transports = ["tcp"]
default_unit = 1
unit_ids = [0, 255]
"#;

fn parse(body: &str) -> Result<Profile, ProfileError> {
    Profile::parse("t.toml", &format!("{DEVICE}{body}"))
}

fn ok(body: &str) -> Profile {
    parse(body).unwrap_or_else(|e| panic!("{e}\n{body}"))
}

/// The line of `needle` in the text `parse` builds.
fn line_of(body: &str, needle: &str) -> usize {
    let text = format!("{DEVICE}{body}");
    let at = text
        .find(needle)
        .unwrap_or_else(|| panic!("`{needle}` in {body}"));
    text[..at].matches('\n').count() + 1
}

#[test]
fn the_generic_profile_written_with_blocks_is_the_one_written_out() {
    let (name, text) = Corpus::Embedded
        .file("profiles", "generic")
        .expect("generic profile");
    let new = Profile::parse(&name, &text).unwrap_or_else(|e| panic!("{e}"));
    let old = Profile::parse(
        "generic_one_entry_per_line.toml",
        include_str!("../data/generic_one_entry_per_line.toml"),
    )
    .unwrap_or_else(|e| panic!("{e}"));
    // The full function code set (FC 07-18 and their tables) is written the same way in both files: the
    // blocks save the 400 entries of the data model, some 380 lines.
    assert!(
        text.lines().count() + 350
            < include_str!("../data/generic_one_entry_per_line.toml")
                .lines()
                .count(),
        "the block form is much shorter"
    );
    assert_eq!(new.device, old.device);
    assert_eq!(new.serial, old.serial);
    assert_eq!(new.functions, old.functions);
    assert_eq!(new.exceptions, old.exceptions);
    assert_eq!(new.identification, old.identification);
    assert_eq!(new.diagnostics, old.diagnostics);
    assert_eq!(new.sdo_errors, old.sdo_errors);
    assert_eq!(new.watchdog, old.watchdog);
    assert_eq!(new.draft, old.draft);
    for (what, a, b) in [
        ("register", new.registers.len(), old.registers.len()),
        ("coil", new.coils.len(), old.coils.len()),
        (
            "discrete input",
            new.discrete_inputs.len(),
            old.discrete_inputs.len(),
        ),
        ("reserved", new.reserved.len(), old.reserved.len()),
        ("mnemonic", new.mnemonics.len(), old.mnemonics.len()),
        ("object", new.objects.len(), old.objects.len()),
    ] {
        assert_eq!(a, b, "{what} count");
    }
    assert_eq!(new.registers.len(), 200);
    // Field by field, in order: the order is the catalog's case order.
    for (i, (a, b)) in new.registers.iter().zip(&old.registers).enumerate() {
        let (a, b) = (a.get_ref(), b.get_ref());
        assert_eq!(a.address, b.address, "register #{i}");
        assert_eq!(a.width, b.width, "register #{i} width");
        assert_eq!(a.name, b.name, "register #{i} name");
        assert_eq!(a.mnemonic, b.mnemonic, "register #{i} mnemonic");
        assert_eq!(a.access, b.access, "register #{i} access");
        assert_eq!(a.signed, b.signed, "register #{i} signed");
        assert_eq!((a.min, a.max), (b.min, b.max), "register #{i} range");
        assert_eq!(a.range(), b.range(), "register #{i} effective range");
        assert_eq!(a.default, b.default, "register #{i} default");
        assert_eq!(a.table, b.table, "register #{i} table");
        assert_eq!(
            (a.motion, a.destructive),
            (b.motion, b.destructive),
            "register #{i} tags"
        );
        assert_eq!(a, b, "register #{i}");
    }
    for (list, what) in [
        ((&new.coils, &old.coils), "coil"),
        (
            (&new.discrete_inputs, &old.discrete_inputs),
            "discrete input",
        ),
    ] {
        for (i, (a, b)) in list.0.iter().zip(list.1.iter()).enumerate() {
            assert_eq!(a.get_ref(), b.get_ref(), "{what} #{i}");
        }
    }
    assert_eq!(new, old, "the whole profile");
}

#[test]
fn blocks_expand_in_address_order_with_templates() {
    let p = ok(r#"
[[register]]
address = 0x100
count = 3
width = 2
name = "Position {n} ({hex})"
mnemonic = "P{i}"
access = "rw"
signed = true
min = -1000
max = 1000
default = "{i}"
description = "set point {n}"

[[register]]
address = 0x200
end = 0x209
stride = 4
width = 2
name = "Speed {i}"
access = "ro"

[[coil]]
address = 10
end = 13
name = "Output {n}"

[[discrete_input]]
address = 0
count = 2
stride = 8
name = "Input {address}"
access = "ro"
"#);
    let regs: Vec<_> = p.registers.iter().map(|r| r.get_ref()).collect();
    let got: Vec<_> = regs
        .iter()
        .map(|r| {
            (
                r.address,
                r.width,
                r.name.as_str(),
                r.mnemonic.as_deref(),
                r.default,
            )
        })
        .collect();
    assert_eq!(
        got,
        [
            (0x100, 2, "Position 1 (0x0100)", Some("P0"), Some(0)),
            (0x102, 2, "Position 2 (0x0102)", Some("P1"), Some(1)),
            (0x104, 2, "Position 3 (0x0104)", Some("P2"), Some(2)),
            (0x200, 2, "Speed 0", None, None),
            (0x204, 2, "Speed 1", None, None),
            (0x208, 2, "Speed 2", None, None),
        ]
    );
    assert!(
        regs[..3]
            .iter()
            .all(|r| r.signed && r.range() == (-1000, 1000) && r.access == Access::Rw)
    );
    assert_eq!(regs[2].description.as_deref(), Some("set point 3"));
    assert!(regs.iter().all(|r| r.confirmed));
    let coils: Vec<(u16, &str, Access)> = p
        .coils
        .iter()
        .map(|c| {
            (
                c.get_ref().address,
                c.get_ref().name.as_str(),
                c.get_ref().access,
            )
        })
        .collect();
    assert_eq!(
        coils,
        [
            (10, "Output 1", Access::Rw),
            (11, "Output 2", Access::Rw),
            (12, "Output 3", Access::Rw),
            (13, "Output 4", Access::Rw)
        ]
    );
    let inputs: Vec<(u16, &str)> = p
        .discrete_inputs
        .iter()
        .map(|c| (c.get_ref().address, c.get_ref().name.as_str()))
        .collect();
    assert_eq!(inputs, [(0, "Input 0"), (8, "Input 8")]);
    // A single entry is a block of one; `count = 1` says the same.
    let one =
        ok("[[register]]\naddress = 5\ncount = 1\nwidth = 1\nname = \"R\"\naccess = \"rw\"\n");
    assert_eq!(one.registers.len(), 1);
    assert_eq!(
        one.register_at(5, false).map(|r| r.name.as_str()),
        Some("R")
    );
}

#[test]
fn unconfirmed_entries_may_leave_width_and_access_out() {
    let p = ok(r#"
[[register]]
address = 0
count = 4
name = "Holding register {address}"
table = "holding"
confirmed = false

[[coil]]
address = 0
count = 2
name = "Coil {address}"
confirmed = false

[[function]]
code = 0x03
name = "Read Holding Registers"
confirmed = false

[[identification]]
object_id = 0
name = "VendorName"
value = "ACME"
confirmed = false

[draft]
target = "tcp://127.0.0.1:502"
scan = [0, 0xFF]
unsupported_functions = [0x07, 0x11]
"#);
    let r = p.registers[0].get_ref();
    assert_eq!(
        (r.width, r.access, r.confirmed, r.table),
        (1, Access::Ro, false, Table::Holding)
    );
    assert!(p.coils.iter().all(|c| !c.get_ref().confirmed));
    assert!(!p.functions[0].confirmed && !p.identification[0].confirmed);
    let d = p.draft.as_ref().expect("draft");
    assert!(d.scanned(0) && d.scanned(0xFF) && !d.scanned(0x100));
    assert_eq!(d.unsupported_functions.len(), 2);
    // Everything else is confirmed unless it says otherwise.
    let p = ok("[[function]]\ncode = 3\nname = \"x\"\n");
    assert!(p.functions[0].confirmed && p.draft.is_none());
}

#[test]
fn bad_profiles_name_the_file_the_line_and_the_reason() {
    let reg = |extra: &str| {
        format!(
            "\n[[register]]\naddress = 0x10\nwidth = 1\nname = \"R {{i}}\"\naccess = \"rw\"\n{extra}"
        )
    };
    // (body, text on the line the error names, what the reason says)
    let cases: Vec<(String, &str, &str)> = vec![
        (reg("cuont = 3\n"), "cuont", "unknown field `cuont`"),
        (reg("count = 2\nend = 0x11\n"), "[[register]]", "give `count` or `end`, not both"),
        (reg("count = 0\n"), "[[register]]", "count 0"),
        (reg("end = 0x0F\n"), "[[register]]", "end 0x000F is before the end of the first entry"),
        (reg("end = 0x13\nstride = 2\n"), "[[register]]", "end 0x0013 is not the last address of an entry"),
        (reg("count = 2\nstride = 0\n"), "[[register]]", "stride 0"),
        (
            "\n[[register]]\naddress = 0\ncount = 2\nwidth = 2\nstride = 1\nname = \"R {i}\"\naccess = \"rw\"\n".into(),
            "[[register]]",
            "stride 1 is less than width 2",
        ),
        (reg("count = 0x10000\n"), "[[register]]", "register block from 0x0010 `R {i}`: 65536 entries every 1 from 0x0010 run past address 0xFFFF"),
        (
            "\n[[register]]\naddress = 0xFFFF\nwidth = 2\nname = \"R\"\naccess = \"rw\"\n".into(),
            "[[register]]",
            "register 0xFFFF `R`: width 2 runs past address 0xFFFF",
        ),
        (
            "\n[[register]]\naddress = 0\ncount = 2\nwidth = 1\nname = \"Same\"\naccess = \"rw\"\n".into(),
            "[[register]]",
            "2 registers would share one name",
        ),
        (reg("count = 2\nmnemonic = \"VM\"\n"), "[[register]]", "share the mnemonic `VM`"),
        (
            "\n[[register]]\naddress = 0\ncount = 2\nwidth = 1\nname = \"R {idx}\"\naccess = \"rw\"\n".into(),
            "[[register]]",
            "unknown placeholder `{idx}`",
        ),
        (reg("count = 2\ndefault = \"x{i}\"\n"), "[[register]]", "default `x{i}` gives `x0` for register 0x0010, not an integer"),
        (
            "\n[[register]]\naddress = 0\nwidth = 1\nname = \"R\"\n".into(),
            "[[register]]",
            "no `access` (ro, rw or wo); only an unconfirmed entry",
        ),
        (
            "\n[[register]]\naddress = 0\naccess = \"ro\"\nname = \"R\"\n".into(),
            "[[register]]",
            "no `width` (1 or 2 registers)",
        ),
        (reg("").replace("width = 1", "width = 3"), "[[register]]", "width 3 (must be 1 or 2 registers)"),
        (reg("access2 = 1\n").replace("access2 = 1\n", "access = \"rx\"\n").replace("access = \"rw\"\n", ""), "access = \"rx\"", "unknown variant `rx`"),
        (reg("min = 5\nmax = 4\n"), "[[register]]", "min 5 > max 4"),
        (reg("max = 70000\n"), "[[register]]", "does not fit unsigned 16-bit"),
        (reg("min = 1\nmax = 9\ndefault = 10\n"), "[[register]]", "default 10 outside 1..=9"),
        (
            format!("{}\n[[register]]\naddress = 0x0F\nwidth = 2\nname = \"Pair\"\naccess = \"rw\"\n", reg("count = 4\n")),
            "address = 0x0F",
            "register 0x000F `Pair` (width 2) overlaps register 0x0010 `R 0`",
        ),
        (
            format!("{}\n[[register]]\naddress = 0x13\nwidth = 1\nname = \"One\"\naccess = \"rw\"\n", reg("count = 4\n")),
            "address = 0x13",
            "register 0x0013 `One` overlaps register 0x0013 `R 3`",
        ),
        (
            "\n[[coil]]\naddress = 0\ncount = 8\nname = \"C{i}\"\n\n[[coil]]\naddress = 5\nname = \"Again\"\n".into(),
            "address = 5",
            "coil 5 defined twice",
        ),
        (
            "\n[[discrete_input]]\naddress = 0\ncount = 2\nname = \"I\"\n".into(),
            "[[discrete_input]]",
            "discrete input block from 0 `I`: 2 entries would share one name",
        ),
        ("\n[[coil]]\naddress = 0\nend = 0x10000\nname = \"C{i}\"\n".into(), "end = 0x10000", "integer `65536`, expected u16"),
        (
            "\n[draft]\ntarget = \"x\"\nscan = [9, 3]\n".into(),
            "[draft]",
            "draft.scan [9, 3] is not an ascending range",
        ),
        (
            "\n[[function]]\ncode = 7\nname = \"x\"\n\n[draft]\ntarget = \"x\"\nscan = [0, 3]\nunsupported_functions = [7]\n".into(),
            "[draft]",
            "function 0x07 is in draft.unsupported_functions and has a [[function]] entry",
        ),
        ("\n[draft]\ntarget = \"x\"\nscan = [0, 3]\nscan_end = 4\n".into(), "scan_end", "unknown field `scan_end`"),
    ];
    for (body, at, want) in &cases {
        let err = match parse(body) {
            Ok(_) => panic!("accepted:\n{body}"),
            Err(e) => e,
        };
        let ProfileError::Invalid { path, line, reason } = &err else {
            panic!("not a validation error: {err}");
        };
        assert_eq!(path, "t.toml");
        assert!(
            reason.contains(want),
            "reason `{reason}` lacks `{want}` for\n{body}"
        );
        let text = format!("{DEVICE}{body}");
        let expected = line_of(body, at);
        // The error names the table (its header or first key) or the key at fault.
        let named = text.lines().nth(line - 1).unwrap_or("");
        assert!(
            *line == expected || (*line + 1 == expected && named.starts_with('[')),
            "line {line} (`{named}`), expected {expected} (`{at}`) for `{reason}` in\n{text}"
        );
        assert!(
            err.to_string().starts_with(&format!("t.toml:{line}: ")),
            "{err}"
        );
    }
}

#[test]
fn shared_io_points_need_a_setup_mnemonic_for_each_point_and_as_many_inputs_as_outputs() {
    let coils = "\n[[coil]]\naddress = 0\ncount = 2\nname = \"Output {n}\"\n";
    let inputs = "\n[[discrete_input]]\naddress = 0\ncount = 2\nname = \"Input {n}\"\n";
    let setup = |k: u32| {
        format!("\n[[mnemonic]]\nname = \"S{k}\"\nread = true\nwrite = true\nformat = \"=A,B,C\"\n")
    };
    let shared = "shared_io_points = true\n";
    let whole = format!("{shared}{coils}{inputs}{}{}", setup(1), setup(2));
    assert!(ok(&whole).device.shared_io_points);
    assert!(
        !ok(&format!("{coils}{inputs}{}", setup(1)))
            .device
            .shared_io_points
    );
    for (body, want) in [
        (
            format!("{shared}{coils}{}{}", setup(1), setup(2)),
            "needs as many discrete inputs as coils, at least one (has 2 coils, 0 discrete inputs)",
        ),
        (
            format!("{shared}{coils}{inputs}{}", setup(1)),
            "point 2 has no read/write setup mnemonic `S2`",
        ),
        (
            whole.replace("name = \"S2\"\nread = true", "name = \"S2\"\nread = false"),
            "point 2 has no read/write setup mnemonic `S2`",
        ),
    ] {
        match parse(&body) {
            Err(ProfileError::Invalid { line, reason, .. }) => {
                assert!(reason.contains(want), "`{reason}` lacks `{want}`");
                assert_eq!(line, 1, "{reason}: the error names [device]");
            }
            other => panic!("{body}\nnot refused: {other:?}"),
        }
    }
}

/// The embedded corpus parses a profile or a golden file once per process and hands out copies: each copy
/// equals what parsing the file gives, a change to one copy does not show in the next, and an unknown name
/// is an error every time it is asked (errors are not kept).
#[test]
fn embedded_profiles_and_golden_files_are_copies_of_one_parse() {
    let corpus = Corpus::Embedded;
    for name in corpus.profile_names() {
        let (file, text) = corpus.file("profiles", &name).expect("the file");
        let parsed = Profile::parse(&file, &text).expect("parses");
        let mut first = corpus.profile(&name).expect("loads");
        assert_eq!(first, parsed, "{name}");
        first.device.id = "changed".into();
        assert_eq!(corpus.profile(&name).expect("loads"), parsed, "{name}");
        let golden = corpus.golden(&name).expect("golden");
        let again = corpus.golden(&name).expect("golden");
        assert_eq!(
            format!("{golden:?}"),
            format!("{again:?}"),
            "{name}'s golden frames"
        );
    }
    for _ in 0..2 {
        assert!(matches!(
            corpus.profile("no-such-drive"),
            Err(drives::corpus::CorpusError::UnknownProfile { .. })
        ));
    }
}

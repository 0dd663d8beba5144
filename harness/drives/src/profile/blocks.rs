//! Register, coil and discrete-input entries as a profile file writes them: one entry, or a block of
//! `count` entries (or up to `end`) from `address` on, `stride` apart, whose text fields are templates.
//! Expanding a block gives the entries one by one, in address order, as if each had been written out.

use serde::Deserialize;
use toml::Spanned;

use super::{Access, Bit, Register, Table};

/// The placeholders a template may use, for error messages.
const PLACEHOLDERS: &str = "{i} (0, 1, ...), {n} (1, 2, ...), {address} (decimal), {hex} (0x0000)";

/// An integer, or a template that gives one (`default = "{address}"`).
#[derive(Clone, Debug, Deserialize)]
#[serde(untagged)]
pub(super) enum IntOrTemplate {
    Int(i64),
    Template(String),
}

/// A `[[register]]` table: one register, or a block of them.
#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RegisterEntry {
    address: u16,
    count: Option<u32>,
    end: Option<u16>,
    stride: Option<u16>,
    width: Option<u8>,
    name: String,
    mnemonic: Option<String>,
    access: Option<Access>,
    #[serde(default)]
    signed: bool,
    min: Option<i64>,
    max: Option<i64>,
    #[serde(default)]
    safe_values: Vec<i64>,
    #[serde(default)]
    operand_open: bool,
    #[serde(default)]
    width_disputed: bool,
    default: Option<IntOrTemplate>,
    unit: Option<String>,
    #[serde(default)]
    table: Table,
    #[serde(default)]
    motion: bool,
    #[serde(default)]
    destructive: bool,
    why: Option<String>,
    group: Option<String>,
    description: Option<String>,
    note: Option<String>,
    line: Option<u32>,
    #[serde(default = "super::yes")]
    confirmed: bool,
    #[serde(default)]
    read_clears: bool,
    condition_flag: Option<u16>,
    #[serde(default)]
    resets_settings: bool,
    #[serde(default)]
    saves_settings: bool,
}

/// A `[[coil]]` or `[[discrete_input]]` table: one bit, or a block of them.
#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct BitEntry {
    address: u16,
    count: Option<u32>,
    end: Option<u16>,
    stride: Option<u16>,
    name: String,
    access: Option<Access>,
    #[serde(default)]
    motion: bool,
    #[serde(default)]
    destructive: bool,
    why: Option<String>,
    note: Option<String>,
    line: Option<u32>,
    #[serde(default = "super::yes")]
    confirmed: bool,
}

/// Where the entries of a block sit: (index, address) of each.
struct Layout {
    addresses: Vec<(u32, u16)>,
}

/// Lay out `address`, `count`/`end`, `stride` for entries `width` addresses wide; `what` names the entry.
fn layout(
    what: &str,
    address: u16,
    count: Option<u32>,
    end: Option<u16>,
    stride: Option<u16>,
    width: u16,
) -> Result<Layout, String> {
    let stride = stride.unwrap_or(width);
    if stride == 0 {
        return Err(format!(
            "{what}: stride 0 (entries must be at least 1 address apart)"
        ));
    }
    if stride < width {
        return Err(format!(
            "{what}: stride {stride} is less than width {width}: the registers of the block would overlap"
        ));
    }
    let count = match (count, end) {
        (Some(_), Some(_)) => {
            return Err(format!(
                "{what}: give `count` or `end`, not both (count = entries, end = last address covered)"
            ));
        }
        (Some(0), None) => return Err(format!("{what}: count 0 (a block has at least one entry)")),
        (Some(c), None) => c,
        (None, None) => 1,
        (None, Some(e)) => {
            let covered = i64::from(e) - i64::from(address) + 1;
            if covered < i64::from(width) {
                return Err(format!(
                    "{what}: end 0x{e:04X} is before the end of the first entry (address 0x{address:04X}, width {width})"
                ));
            }
            let span = covered - i64::from(width);
            if span % i64::from(stride) != 0 {
                return Err(format!(
                    "{what}: end 0x{e:04X} is not the last address of an entry (entries of width {width} every {stride} from 0x{address:04X})"
                ));
            }
            (span / i64::from(stride) + 1) as u32
        }
    };
    let last_end = u64::from(address) + u64::from(count - 1) * u64::from(stride) + u64::from(width);
    if last_end > 0x1_0000 {
        return Err(if count == 1 {
            format!("{what}: width {width} runs past address 0xFFFF")
        } else {
            format!(
                "{what}: {count} entries every {stride} from 0x{address:04X} run past address 0xFFFF"
            )
        });
    }
    Ok(Layout {
        addresses: (0..count)
            .map(|i| (i, (u32::from(address) + i * u32::from(stride)) as u16))
            .collect(),
    })
}

/// Fill a template: `{i}`, `{n}`, `{address}`, `{hex}`; `{{` and `}}` are literal braces.
pub(super) fn fill(template: &str, i: u32, address: u16) -> Result<String, String> {
    let mut out = String::with_capacity(template.len() + 8);
    let mut rest = template;
    while let Some(pos) = rest.find(['{', '}']) {
        out.push_str(&rest[..pos]);
        let tail = &rest[pos..];
        if let Some(t) = tail.strip_prefix("{{") {
            out.push('{');
            rest = t;
        } else if let Some(t) = tail.strip_prefix("}}") {
            out.push('}');
            rest = t;
        } else if tail.starts_with('}') {
            return Err(format!(
                "`{template}`: a lone `}}` (write `}}}}` for a literal brace)"
            ));
        } else {
            let Some(close) = tail.find('}') else {
                return Err(format!(
                    "`{template}`: `{{` without `}}` (write `{{{{` for a literal brace)"
                ));
            };
            let key = &tail[1..close];
            match key {
                "i" => out.push_str(&i.to_string()),
                "n" => out.push_str(&(u64::from(i) + 1).to_string()),
                "address" => out.push_str(&address.to_string()),
                "hex" => out.push_str(&format!("0x{address:04X}")),
                other => {
                    return Err(format!(
                        "`{template}`: unknown placeholder `{{{other}}}` (known: {PLACEHOLDERS})"
                    ));
                }
            }
            rest = &tail[close + 1..];
        }
    }
    out.push_str(rest);
    Ok(out)
}

/// True when a template has a placeholder (so the entries of a block get different text). A template that
/// does not fill counts as having one: filling it reports what is wrong with it.
fn has_placeholder(template: &str) -> bool {
    match (fill(template, 0, 0), fill(template, 1, 1)) {
        (Ok(a), Ok(b)) => a != b,
        _ => true,
    }
}

/// Fill an optional template.
fn fill_opt(t: &Option<String>, i: u32, address: u16) -> Result<Option<String>, String> {
    t.as_deref().map(|t| fill(t, i, address)).transpose()
}

/// A register entry for messages: `register 0x0010 `Speed`` or `register block from 0x0000 `R {i}``.
fn describe(kind: &str, address: u16, name: &str, count: usize) -> String {
    if count > 1 {
        format!("{kind} block from 0x{address:04X} `{name}`")
    } else {
        format!("{kind} 0x{address:04X} `{name}`")
    }
}

impl RegisterEntry {
    /// The registers of the entry; the error is the reason, the caller adds the line.
    pub(super) fn expand(&self) -> Result<Vec<Register>, String> {
        let block = self.count.is_some_and(|c| c != 1) || self.end.is_some();
        let first = describe(
            "register",
            self.address,
            &self.name,
            if block { 2 } else { 1 },
        );
        let width = match (self.width, self.confirmed) {
            (Some(w), _) => w,
            (None, false) => 1,
            (None, true) => {
                return Err(format!(
                    "{first}: no `width` (1 or 2 registers); only an unconfirmed entry (confirmed = false) may leave it out"
                ));
            }
        };
        let access = match (self.access, self.confirmed) {
            (Some(a), _) => a,
            (None, false) => Access::Ro,
            (None, true) => {
                return Err(format!(
                    "{first}: no `access` (ro, rw or wo); only an unconfirmed entry (confirmed = false) may leave it out"
                ));
            }
        };
        if width != 1 && width != 2 {
            return Err(format!("{first}: width {width} (must be 1 or 2 registers)"));
        }
        let layout = layout(
            &first,
            self.address,
            self.count,
            self.end,
            self.stride,
            u16::from(width),
        )?;
        let n = layout.addresses.len();
        let what = describe("register", self.address, &self.name, n);
        if n > 1 {
            if !has_placeholder(&self.name) {
                return Err(format!(
                    "{what}: {n} registers would share one name: put a placeholder in it ({PLACEHOLDERS})"
                ));
            }
            if let Some(m) = &self.mnemonic
                && !has_placeholder(m)
            {
                return Err(format!(
                    "{what}: {n} registers would share the mnemonic `{m}`: put a placeholder in it or give each register its own entry"
                ));
            }
        }
        let mut out = Vec::with_capacity(n);
        for (i, address) in layout.addresses {
            let err = |e: String| format!("{what}: {e}");
            let default = match &self.default {
                None => None,
                Some(IntOrTemplate::Int(v)) => Some(*v),
                Some(IntOrTemplate::Template(t)) => {
                    let text = fill(t, i, address).map_err(err)?;
                    Some(text.trim().parse::<i64>().map_err(|_| {
                        format!(
                            "{what}: default `{t}` gives `{text}` for register 0x{address:04X}, not an integer"
                        )
                    })?)
                }
            };
            out.push(Register {
                address,
                width,
                name: fill(&self.name, i, address).map_err(err)?,
                mnemonic: fill_opt(&self.mnemonic, i, address).map_err(err)?,
                access,
                signed: self.signed,
                min: self.min,
                max: self.max,
                safe_values: self.safe_values.clone(),
                operand_open: self.operand_open,
                width_disputed: self.width_disputed,
                default,
                unit: self.unit.clone(),
                table: self.table,
                motion: self.motion,
                destructive: self.destructive,
                why: self.why.clone(),
                group: fill_opt(&self.group, i, address).map_err(err)?,
                description: fill_opt(&self.description, i, address).map_err(err)?,
                note: fill_opt(&self.note, i, address).map_err(err)?,
                line: self.line,
                confirmed: self.confirmed,
                read_clears: self.read_clears,
                condition_flag: self.condition_flag,
                resets_settings: self.resets_settings,
                saves_settings: self.saves_settings,
            });
        }
        Ok(out)
    }
}

impl BitEntry {
    /// The bits of the entry (`kind`: "coil" or "discrete input"); the error is the reason.
    pub(super) fn expand(&self, kind: &str) -> Result<Vec<Bit>, String> {
        let block = self.count.is_some_and(|c| c != 1) || self.end.is_some();
        let first = if block {
            format!("{kind} block from {} `{}`", self.address, self.name)
        } else {
            format!("{kind} {} `{}`", self.address, self.name)
        };
        let layout = layout(&first, self.address, self.count, self.end, self.stride, 1)?;
        let n = layout.addresses.len();
        if n > 1 && !has_placeholder(&self.name) {
            return Err(format!(
                "{kind} block from {} `{}`: {n} entries would share one name: put a placeholder in it ({PLACEHOLDERS})",
                self.address, self.name
            ));
        }
        let mut out = Vec::with_capacity(n);
        for (i, address) in layout.addresses {
            let err = |e: String| format!("{kind} block from {}: {e}", self.address);
            out.push(Bit {
                address,
                name: fill(&self.name, i, address).map_err(err)?,
                // Coils are read/write unless they say; an unconfirmed bit is never written.
                access: self.access.unwrap_or(if self.confirmed {
                    Access::Rw
                } else {
                    Access::Ro
                }),
                motion: self.motion,
                destructive: self.destructive,
                why: self.why.clone(),
                note: fill_opt(&self.note, i, address).map_err(err)?,
                line: self.line,
                confirmed: self.confirmed,
            });
        }
        Ok(out)
    }
}

/// Expand spanned entries, each expanded entry keeping its table's span.
pub(super) fn expand_all<E, T>(
    entries: Vec<Spanned<E>>,
    mut expand: impl FnMut(&E) -> Result<Vec<T>, String>,
) -> Result<Vec<Spanned<T>>, (usize, String)> {
    let mut out = Vec::new();
    for e in entries {
        let span = e.span();
        let items = expand(e.get_ref()).map_err(|reason| (span.start, reason))?;
        out.extend(items.into_iter().map(|t| Spanned::new(span.clone(), t)));
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::fill;

    #[test]
    fn templates_fill_every_placeholder_and_name_the_bad_ones() {
        assert_eq!(
            fill("Reg {i}/{n} at {address} ({hex})", 2, 42).unwrap(),
            "Reg 2/3 at 42 (0x002A)"
        );
        assert_eq!(fill("{{literal}} {address}", 0, 7).unwrap(), "{literal} 7");
        assert_eq!(fill("no placeholder", 5, 5).unwrap(), "no placeholder");
        assert!(
            fill("x {idx}", 0, 0)
                .unwrap_err()
                .contains("unknown placeholder `{idx}`")
        );
        assert!(fill("x {i", 0, 0).unwrap_err().contains("without"));
        assert!(fill("x }", 0, 0).unwrap_err().contains("lone"));
    }
}

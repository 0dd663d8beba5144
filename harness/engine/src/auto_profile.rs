//! `--profile auto`: the profile whose device identification (FC 2B/0E) the drive gives, vendor name AND
//! product code, compared exactly after trimming and ignoring case. No match and an ambiguous match are
//! errors that show what the drive said and how to name a profile; there is no fallback (in particular not to
//! `generic`, which marks nothing as motion).

use drives::profile::Profile;

/// The identification objects that must both match.
const VENDOR: u8 = 0x00;
const PRODUCT: u8 = 0x01;

/// The profile `auto` picked and the objects that matched (id, name, value).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct AutoMatch {
    pub profile: String,
    pub matched: Vec<(u8, String, String)>,
}

fn norm(s: &str) -> String {
    s.trim().to_lowercase()
}

fn object_name(id: u8) -> &'static str {
    match id {
        0x00 => "VendorName",
        0x01 => "ProductCode",
        0x02 => "MajorMinorRevision",
        0x03 => "VendorUrl",
        0x04 => "ProductName",
        0x05 => "ModelName",
        0x06 => "UserApplicationName",
        _ => "object",
    }
}

/// The identification as read, for messages.
pub fn describe(found: &[(u8, String)]) -> String {
    if found.is_empty() {
        return "no objects".into();
    }
    found
        .iter()
        .map(|(id, v)| format!("{} (0x{id:02X}) = {v:?}", object_name(*id)))
        .collect::<Vec<_>>()
        .join(", ")
}

fn wants(p: &Profile, id: u8) -> Option<&str> {
    p.identification
        .iter()
        .find(|o| o.object_id == id)
        .map(|o| o.value.as_str())
}

/// Pick the one profile of `profiles` whose vendor name and product code equal the drive's `found` objects.
pub fn pick(found: &[(u8, String)], profiles: &[Profile]) -> Result<AutoMatch, String> {
    let got = |id: u8| {
        found
            .iter()
            .find(|(i, v)| *i == id && !v.trim().is_empty())
            .map(|(_, v)| v.as_str())
    };
    let mut candidates = Vec::new();
    if let (Some(vendor), Some(product)) = (got(VENDOR), got(PRODUCT)) {
        for p in profiles {
            if let (Some(v), Some(c)) = (wants(p, VENDOR), wants(p, PRODUCT))
                && norm(v) == norm(vendor)
                && norm(c) == norm(product)
            {
                candidates.push(AutoMatch {
                    profile: p.device.id.clone(),
                    matched: vec![
                        (VENDOR, object_name(VENDOR).into(), vendor.to_string()),
                        (PRODUCT, object_name(PRODUCT).into(), product.to_string()),
                    ],
                });
            }
        }
    }
    let known = profiles
        .iter()
        .map(|p| match (wants(p, VENDOR), wants(p, PRODUCT)) {
            (Some(v), Some(c)) => format!("{} ({v:?} / {c:?})", p.device.id),
            _ => format!("{} (no identification)", p.device.id),
        })
        .collect::<Vec<_>>()
        .join(", ");
    let how = "name the profile with --profile NAME|PATH (a corpus profile, or a profile file of your drive: draft one with `modbus-harness probe --target URL --write-profile my.toml`)";
    match candidates.len() {
        1 => Ok(candidates.remove(0)),
        0 => Err(format!(
            "no profile matches the device identification: {}. A profile matches only when both its vendor name (0x00) and product code (0x01) equal the drive's (trimmed, ignoring case). Known profiles (vendor / product code): {known}. There is no fallback: {how}",
            describe(found)
        )),
        _ => Err(format!(
            "the device identification {} matches several profiles ({}): {how}",
            describe(found),
            candidates
                .iter()
                .map(|c| c.profile.as_str())
                .collect::<Vec<_>>()
                .join(", ")
        )),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use drives::corpus::Corpus;

    fn profiles() -> Vec<Profile> {
        let c = Corpus::Embedded;
        c.profile_names()
            .iter()
            .map(|n| c.profile(n).expect("profile"))
            .collect()
    }

    fn ids(v: &[(u8, &str)]) -> Vec<(u8, String)> {
        v.iter().map(|(i, s)| (*i, s.to_string())).collect()
    }

    #[test]
    fn an_exact_vendor_and_product_code_match_picks_the_profile() {
        let m = pick(
            &ids(&[(0, "  sem usa "), (1, "MDRIVE P/N"), (2, "9.9")]),
            &profiles(),
        )
        .expect("match");
        assert_eq!(m.profile, "mdrive");
        assert_eq!(m.matched.len(), 2);
        let m = pick(&ids(&[(0, "IMS USA"), (1, "LMDxExxx")]), &profiles()).expect("match");
        assert_eq!(m.profile, "lmd");
    }

    #[test]
    fn a_revision_or_a_substring_does_not_match() {
        // A revision containing "1.0" (generic's revision) matched generic before; now nothing matches.
        let e = pick(&ids(&[(0, "ACME"), (1, "X1"), (2, "1.0")]), &profiles()).unwrap_err();
        assert!(
            e.contains("no profile matches") && e.contains("\"1.0\""),
            "{e}"
        );
        assert!(e.contains("--profile NAME|PATH"), "{e}");
        // Substrings either way, or the vendor alone, are not matches.
        assert!(pick(&ids(&[(0, "SEM"), (1, "MDrive P/N")]), &profiles()).is_err());
        assert!(pick(&ids(&[(0, "SEM USA Inc"), (1, "MDrive P/N")]), &profiles()).is_err());
        assert!(pick(&ids(&[(0, "SEM USA")]), &profiles()).is_err());
        assert!(pick(&ids(&[(0, "SEM USA"), (1, "MDrive")]), &profiles()).is_err());
    }

    #[test]
    fn two_profiles_with_the_same_identification_are_ambiguous() {
        let mut ps = profiles();
        let mut twin = ps.iter().find(|p| p.device.id == "mdrive").unwrap().clone();
        twin.device.id = "mdrive-twin".into();
        ps.push(twin);
        let e = pick(&ids(&[(0, "SEM USA"), (1, "MDrive P/N")]), &ps).unwrap_err();
        assert!(
            e.contains("several profiles") && e.contains("mdrive-twin"),
            "{e}"
        );
    }
}

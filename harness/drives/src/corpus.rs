//! The corpus: data files under corpus/, embedded at build time or read from a directory the user names.

use std::path::Path;

use crate::golden::{GoldenFile, LoadError};
use crate::profile::{Profile, ProfileError};

mod embedded {
    include!(concat!(env!("OUT_DIR"), "/corpus_files.rs"));
}

/// Why a profile or a golden file could not be had from a corpus.
#[derive(Debug, thiserror::Error)]
pub enum CorpusError {
    #[error("no profile `{name}` in the {corpus}; known profiles: {}", known.join(", "))]
    UnknownProfile {
        name: String,
        corpus: String,
        known: Vec<String>,
    },
    #[error("reading the {corpus}: {source}")]
    Read {
        corpus: String,
        source: std::io::Error,
    },
    #[error(transparent)]
    Profile(#[from] ProfileError),
    #[error(transparent)]
    Golden(#[from] LoadError),
}

/// True when a `--profile` value or the profile of a `sim:` target names a file rather than a profile of the
/// corpus: it contains a `/` (or a backslash), or it ends in `.toml`. `./my.toml`, `/etc/drive.toml`, `my.toml`
/// and `profiles/x` are files; `mdrive` is the corpus profile of that name.
pub fn is_profile_path(s: &str) -> bool {
    s.contains('/') || s.contains('\\') || s.ends_with(".toml")
}

/// What the embedded corpus gave for a name, parsed once per process (the embedded files never change).
type Parsed<T> = std::sync::Mutex<std::collections::HashMap<String, T>>;
static EMBEDDED_PROFILES: std::sync::OnceLock<Parsed<Profile>> = std::sync::OnceLock::new();
static EMBEDDED_GOLDEN: std::sync::OnceLock<Parsed<Option<GoldenFile>>> =
    std::sync::OnceLock::new();

/// A copy of what `parse` gave for `name` the first time: errors are not kept (an unknown name is asked
/// again, and says so again).
fn embedded_once<T: Clone>(
    name: &str,
    cache: &std::sync::OnceLock<Parsed<T>>,
    parse: impl FnOnce() -> Result<T, CorpusError>,
) -> Result<T, CorpusError> {
    let cache = cache.get_or_init(Default::default);
    if let Some(v) = cache
        .lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner)
        .get(name)
    {
        return Ok(v.clone());
    }
    // Parsed outside the lock: two threads asking at once may both parse; either copy is the same.
    let v = parse()?;
    cache
        .lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner)
        .entry(name.to_string())
        .or_insert_with(|| v.clone());
    Ok(v)
}

/// Where corpus files come from.
#[derive(Clone, Debug)]
pub enum Corpus {
    /// The files built into the binary.
    Embedded,
    /// A directory laid out like corpus/.
    Dir(std::path::PathBuf),
}

impl Corpus {
    /// The embedded corpus, or `dir` when given.
    pub fn from_option(dir: Option<&Path>) -> Self {
        match dir {
            Some(d) => Corpus::Dir(d.to_path_buf()),
            None => Corpus::Embedded,
        }
    }

    /// (name, text) of every `.toml` under `sub` (e.g. "golden"), sorted by name.
    pub fn files(&self, sub: &str) -> std::io::Result<Vec<(String, String)>> {
        match self {
            Corpus::Embedded => Ok(embedded::FILES
                .iter()
                .filter(|(p, _)| p.starts_with(&format!("{sub}/")))
                .map(|(p, t)| (format!("corpus/{p} (embedded)"), t.to_string()))
                .collect()),
            Corpus::Dir(d) => {
                let dir = d.join(sub);
                let mut out = Vec::new();
                for e in std::fs::read_dir(&dir)? {
                    let p = e?.path();
                    if p.extension().is_some_and(|x| x == "toml") {
                        out.push((p.display().to_string(), std::fs::read_to_string(&p)?));
                    }
                }
                out.sort();
                Ok(out)
            }
        }
    }

    /// The text of one file, e.g. ("profiles", "sd2x").
    pub fn file(&self, sub: &str, stem: &str) -> std::io::Result<(String, String)> {
        let want = format!("{stem}.toml");
        self.files(sub)?
            .into_iter()
            .find(|(n, _)| {
                Path::new(n.trim_end_matches(" (embedded)"))
                    .file_name()
                    .is_some_and(|f| f.to_string_lossy() == want)
            })
            .ok_or_else(|| {
                std::io::Error::new(
                    std::io::ErrorKind::NotFound,
                    format!("no {sub}/{want} in the {}", self.describe()),
                )
            })
    }

    /// A phrase naming the corpus for messages.
    pub fn describe(&self) -> String {
        match self {
            Corpus::Embedded => "embedded corpus".into(),
            Corpus::Dir(d) => format!("corpus at {}", d.display()),
        }
    }
}

impl Corpus {
    /// The names of the profiles (file stems of `profiles/*.toml`).
    pub fn profile_names(&self) -> Vec<String> {
        self.files("profiles")
            .unwrap_or_default()
            .iter()
            .filter_map(|(n, _)| {
                Path::new(n.trim_end_matches(" (embedded)"))
                    .file_stem()
                    .map(|s| s.to_string_lossy().into_owned())
            })
            .collect()
    }

    /// Load and validate the profile `name`; an unknown name lists the known ones. An embedded profile is
    /// parsed once per process and copied after that (parsing takes about 10 ms, a copy about 60 µs; a
    /// process that runs many sessions, as the tests and a fuzz target do, loaded it for each).
    pub fn profile(&self, name: &str) -> Result<Profile, CorpusError> {
        if let Corpus::Embedded = self {
            return embedded_once(name, &EMBEDDED_PROFILES, || self.parse_profile(name));
        }
        self.parse_profile(name)
    }

    fn parse_profile(&self, name: &str) -> Result<Profile, CorpusError> {
        // Read the directory first: a corpus that cannot be read is not an unknown profile.
        self.files("profiles").map_err(|source| CorpusError::Read {
            corpus: self.describe(),
            source,
        })?;
        let (file, text) =
            self.file("profiles", name)
                .map_err(|_| CorpusError::UnknownProfile {
                    name: name.to_string(),
                    corpus: self.describe(),
                    known: self.profile_names(),
                })?;
        Ok(Profile::parse(&file, &text)?)
    }

    /// The profile a `--profile` value or a `sim:` target names: a file when [`is_profile_path`] says so
    /// (a missing or invalid file is an error naming it), else the corpus profile of that name.
    pub fn load(&self, name_or_path: &str) -> Result<Profile, CorpusError> {
        if is_profile_path(name_or_path) {
            Ok(Profile::load(Path::new(name_or_path))?)
        } else {
            self.profile(name_or_path)
        }
    }

    /// Every golden file of the corpus, sorted by name.
    pub fn golden_files(&self) -> Result<Vec<GoldenFile>, CorpusError> {
        let files = self.files("golden").map_err(|source| CorpusError::Read {
            corpus: self.describe(),
            source,
        })?;
        files
            .iter()
            .map(|(name, text)| Ok(GoldenFile::parse(name, text)?))
            .collect()
    }

    /// The golden frames of a profile's manual, if the corpus has them (embedded ones parsed once per
    /// process, as profiles are).
    pub fn golden(&self, profile: &str) -> Result<Option<GoldenFile>, CorpusError> {
        if let Corpus::Embedded = self {
            return embedded_once(profile, &EMBEDDED_GOLDEN, || self.parse_golden(profile));
        }
        self.parse_golden(profile)
    }

    fn parse_golden(&self, profile: &str) -> Result<Option<GoldenFile>, CorpusError> {
        match self.file("golden", profile) {
            Ok((file, text)) => Ok(Some(GoldenFile::parse(&file, &text)?)),
            Err(_) => Ok(None),
        }
    }
}

//! The corpus: data files under corpus/, embedded at build time or read from a directory the user names.

use std::path::Path;

mod embedded {
    include!(concat!(env!("OUT_DIR"), "/corpus_files.rs"));
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

//! The site file on the page: read it, check an edited text exactly as `markhold params
//! check` would at the file's place (relative files resolve beside it), and save a text
//! that passes. A saved site takes effect when markhold starts again; the running loop
//! keeps the site it started with.

use std::io::Write;
use std::path::{Path, PathBuf};

use serde::Serialize;

use crate::params::ParamsError;

/// A site file's size limit (the one `params check` applies).
pub const MAX_SITE_BYTES: usize = markhold_config::MAX_CONFIG_FILE_BYTES as usize;

/// One problem, located in the text.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct SiteError {
    /// 1-based line and column, when the error has a place.
    pub line: Option<usize>,
    pub column: Option<usize>,
    /// The dotted key (or `section.key = value: ` of a parse error), when known.
    pub key: String,
    /// The whole message, as `params check` prints it.
    pub message: String,
}

/// The result of checking a site text.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct SiteCheck {
    pub ok: bool,
    pub errors: Vec<SiteError>,
}

/// `GET site.json`.
#[derive(Debug, Clone, Serialize)]
pub struct SiteFile {
    pub path: PathBuf,
    pub text: String,
    pub check: SiteCheck,
}

fn located(e: &ParamsError) -> SiteError {
    let message = e.to_string();
    match e {
        ParamsError::Read { .. } => SiteError {
            line: None,
            column: None,
            key: String::new(),
            message,
        },
        ParamsError::Parse {
            line, column, key, ..
        } => SiteError {
            line: Some(*line),
            column: Some(*column),
            key: key.trim_end_matches(": ").to_string(),
            message,
        },
        ParamsError::Config(c) => SiteError {
            line: c.line,
            column: c.column.map(|c| c as usize),
            key: c.key.clone(),
            message,
        },
        ParamsError::ReferencedFile {
            line, column, key, ..
        } => SiteError {
            line: Some(*line),
            column: Some(*column),
            key: key.clone(),
            message,
        },
    }
}

/// Check `text` as the site file at `path`.
pub fn check(path: &Path, text: &str) -> SiteCheck {
    match crate::params::parse(path, text) {
        Ok(_) => SiteCheck {
            ok: true,
            errors: Vec::new(),
        },
        Err(e) => SiteCheck {
            ok: false,
            errors: vec![located(&e)],
        },
    }
}

/// The site file as it is on disk now, checked.
pub fn read(path: &Path) -> SiteFile {
    match markhold_config::read_regular(path, markhold_config::MAX_CONFIG_FILE_BYTES) {
        Ok(text) => SiteFile {
            path: path.to_path_buf(),
            check: check(path, &text),
            text,
        },
        Err(error) => SiteFile {
            path: path.to_path_buf(),
            text: String::new(),
            check: SiteCheck {
                ok: false,
                errors: vec![located(&ParamsError::Read {
                    file: path.to_path_buf(),
                    error,
                })],
            },
        },
    }
}

/// Why a text was not saved.
#[derive(Debug, thiserror::Error)]
pub enum SaveError {
    #[error("the site does not pass the check")]
    Invalid(SiteCheck),
    #[error("saving {path}: {source}")]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
}

/// Save `text` to `path` if it passes the check: written beside it, synced, then renamed
/// over it (a crash leaves the old file or the new one, never half of one); the old one
/// is kept as `<file>.bak`.
pub fn save(path: &Path, text: &str) -> Result<SiteCheck, SaveError> {
    let c = check(path, text);
    if !c.ok {
        return Err(SaveError::Invalid(c));
    }
    let io = |source| SaveError::Io {
        path: path.to_path_buf(),
        source,
    };
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_else(|| "site.toml".into());
    let tmp = path.with_file_name(format!(".{name}.saving"));
    let mut f = std::fs::File::create(&tmp).map_err(io)?;
    f.write_all(text.as_bytes())
        .and_then(|()| f.sync_all())
        .map_err(io)?;
    drop(f);
    if path.exists() {
        let _ = std::fs::copy(path, path.with_file_name(format!("{name}.bak")));
    }
    std::fs::rename(&tmp, path).map_err(io)?;
    Ok(c)
}

#[cfg(test)]
#[allow(clippy::unwrap_used)] // Tests fail loudly on a broken setup, by design.
mod tests {
    use super::*;

    fn site() -> (PathBuf, String) {
        let p = Path::new(env!("CARGO_MANIFEST_DIR")).join("../params/pool.toml");
        let t = std::fs::read_to_string(&p).unwrap();
        (p, t)
    }

    #[test]
    fn a_bad_value_is_located_at_its_line_and_key() {
        let (p, text) = site();
        assert!(check(&p, &text).ok, "{:?}", check(&p, &text));
        // An unknown key: at its line.
        let bad = text.replacen("[marker]", "[marker]\nsize_mm = 150", 1);
        let c = check(&p, &bad);
        assert!(!c.ok);
        let e = &c.errors[0];
        let line = bad
            .lines()
            .position(|l| l == "size_mm = 150")
            .map(|i| i + 1);
        assert_eq!(e.line, line, "{e:?}");
        assert!(e.message.contains("size_mm"), "{e:?}");
        // A value out of range: its dotted key, at its line.
        let out = text.replacen("distance_m = 1.0", "distance_m = -1.0", 1);
        let c = check(&p, &out);
        let e = &c.errors[0];
        let line = out.lines().position(|l| l.starts_with("distance_m = -1.0"));
        assert_eq!(e.line, line.map(|i| i + 1), "{e:?}");
        assert_eq!(e.key, "station.distance_m", "{e:?}");
    }

    #[test]
    fn an_invalid_text_is_not_saved_and_a_valid_one_replaces_the_file() {
        let (p, text) = site();
        let dir = std::env::temp_dir().join(format!("markhold-web-site-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let target = dir.join("site.toml");
        std::fs::write(&target, &text).unwrap();
        let bad = text.replacen("[exposure]", "[exposure]\nnot_a_key = 1", 1);
        assert!(matches!(save(&target, &bad), Err(SaveError::Invalid(_))));
        assert_eq!(std::fs::read_to_string(&target).unwrap(), text);
        let edited = format!("# edited\n{text}");
        assert!(save(&target, &edited).unwrap().ok);
        assert_eq!(std::fs::read_to_string(&target).unwrap(), edited);
        assert_eq!(
            std::fs::read_to_string(dir.join("site.toml.bak")).unwrap(),
            text
        );
        let _ = p;
        let _ = std::fs::remove_dir_all(&dir);
    }
}

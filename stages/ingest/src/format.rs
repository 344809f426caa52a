//! [`SourceFormat`]: what a recording is, and [`detect`], which tells it from the path.

use std::path::Path;

use crate::error::{Error, Result};

/// What the source is.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Deserialize)]
#[cfg_attr(feature = "node", derive(schemars::JsonSchema))]
#[serde(rename_all = "kebab-case")]
pub enum SourceFormat {
    /// From the path: a folder is a CMU-GPR sequence, else by extension (`.mcap`, `.dzt`, `.dt1`).
    #[default]
    Auto,
    /// An MCAP recording (ours or any ROS 2 recording with these message types).
    Mcap,
    /// A CMU-GPR sequence folder.
    CmuGpr,
    /// GSSI SIR `.DZT`.
    Dzt,
    /// Sensors & Software `.DT1` with its `.HD`.
    Dt1,
}

impl SourceFormat {
    /// This format, or for [`SourceFormat::Auto`] the one [`detect`] tells from `path`.
    ///
    /// # Errors
    /// [`Error::UnknownFormat`] when `Auto` and the path says nothing [`detect`] knows.
    pub fn resolve(self, path: &Path) -> Result<SourceFormat> {
        match self {
            SourceFormat::Auto => detect(path),
            known => Ok(known),
        }
    }
}

/// The format of `path`: a folder is a CMU-GPR sequence, a file goes by its extension
/// (`.mcap`, `.dzt`, `.dt1`, any case). Never [`SourceFormat::Auto`].
///
/// # Errors
/// [`Error::UnknownFormat`] for any other extension.
pub fn detect(path: &Path) -> Result<SourceFormat> {
    if path.is_dir() {
        return Ok(SourceFormat::CmuGpr);
    }
    let ext = path
        .extension()
        .and_then(|e| e.to_str())
        .map(str::to_ascii_lowercase)
        .unwrap_or_default();
    match ext.as_str() {
        "mcap" => Ok(SourceFormat::Mcap),
        "dzt" => Ok(SourceFormat::Dzt),
        "dt1" => Ok(SourceFormat::Dt1),
        _ => Err(Error::UnknownFormat { path: path.into() }),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_extension_tells_the_format_in_any_case() {
        for (name, want) in [
            ("run.mcap", SourceFormat::Mcap),
            ("LINE.DZT", SourceFormat::Dzt),
            ("line.dzt", SourceFormat::Dzt),
            ("LINE01.DT1", SourceFormat::Dt1),
        ] {
            assert_eq!(detect(Path::new(name)).expect(name), want, "{name}");
        }
    }

    #[test]
    fn a_folder_is_a_cmu_sequence_and_an_explicit_format_is_kept() {
        let dir = tempfile::tempdir().expect("temp dir");
        assert_eq!(detect(dir.path()).expect("folder"), SourceFormat::CmuGpr);
        assert_eq!(
            SourceFormat::Dzt.resolve(Path::new("notes.txt")).expect("explicit"),
            SourceFormat::Dzt
        );
    }

    #[test]
    fn an_unknown_extension_is_refused_naming_the_file() {
        for name in ["notes.txt", "no_extension"] {
            let e = detect(Path::new(name)).expect_err(name);
            assert!(matches!(e, Error::UnknownFormat { .. }), "{e:?}");
            assert!(
                e.to_string().starts_with(&format!("{name}: cannot tell the format")),
                "{e}"
            );
        }
    }
}

use std::fmt;
use std::path::PathBuf;

/// Why a scene could not be loaded. Every variant names the file; parse and
/// validation errors also name the line, column and field.
#[derive(Debug, thiserror::Error)]
pub enum SceneError {
    /// The cause is part of the message and deliberately not a
    /// `source()`: printed as a chain (`{:#}`) it would appear twice.
    #[error("{path}: cannot read scene: {error}", path = .path.display())]
    Io {
        path: PathBuf,
        error: std::io::Error,
    },
    /// TOML syntax errors, wrong types, unknown or missing fields.
    #[error("{path}:{location}: {message}", path = .path.display())]
    Parse {
        path: PathBuf,
        location: Location,
        message: String,
    },
    /// A file given as the scene that is not one (a PLY), or a model file
    /// as a scene that cannot be rendered; the message says why and what
    /// to do.
    #[error("{path}: {message}", path = .path.display())]
    Input { path: PathBuf, message: String },
    /// Well-formed TOML whose values make no scene (negative radius, unknown material, ...).
    #[error("{path}:{location}: {field}: {message}", path = .path.display())]
    Invalid {
        path: PathBuf,
        location: Location,
        field: String,
        message: String,
    },
}

/// 1-based line and column in the scene file.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Location {
    pub line: usize,
    pub column: usize,
}

impl Location {
    /// Line and column of a byte offset in `src`.
    pub fn of_offset(src: &str, offset: usize) -> Self {
        let offset = offset.min(src.len());
        let before = &src[..offset];
        let line = before.matches('\n').count() + 1;
        let column = before.rsplit('\n').next().map_or(0, |l| l.chars().count()) + 1;
        Location { line, column }
    }
}

impl fmt::Display for Location {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}:{}", self.line, self.column)
    }
}

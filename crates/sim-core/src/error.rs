//! Why a scene was rejected, and where: [`SceneError`] names the field ([`FieldPath`]) and,
//! when the scene came from text, the line and column ([`Location`]). Every part of the
//! scene's validation (the scene itself, the sensor and estimator specs) reports through it.

use std::fmt;

/// One step of a path to a field in the scene: a table key or an array index.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum PathSeg {
    /// A table key.
    Key(String),
    /// An array index.
    Index(usize),
}

/// A path to a field, printed as `copter[1].start.pos_m`.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct FieldPath(pub Vec<PathSeg>);

impl FieldPath {
    pub(crate) fn key(mut self, k: &str) -> Self {
        self.0.push(PathSeg::Key(k.into()));
        self
    }
    pub(crate) fn index(mut self, i: usize) -> Self {
        self.0.push(PathSeg::Index(i));
        self
    }
}

impl fmt::Display for FieldPath {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        if self.0.is_empty() {
            return f.write_str("<document>");
        }
        for (i, seg) in self.0.iter().enumerate() {
            match seg {
                PathSeg::Key(k) if i == 0 => write!(f, "{k}")?,
                PathSeg::Key(k) => write!(f, ".{k}")?,
                PathSeg::Index(n) => write!(f, "[{n}]")?,
            }
        }
        Ok(())
    }
}

/// Where in a file something is: 1-based line and column.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Location {
    /// 1-based line.
    pub line: usize,
    /// 1-based column, in characters.
    pub column: usize,
}

/// Why a scene was rejected.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum SceneError {
    /// The text is not valid TOML or does not fit the scene format (wrong type, missing or
    /// unknown field).
    #[error("{origin}:{}: {path}: {message}", fmt_loc(.location))]
    Syntax {
        /// File name or other origin of the text.
        origin: String,
        /// Where, if known.
        location: Option<Location>,
        /// The field (or the enclosing table) at fault.
        path: FieldPath,
        /// What is wrong.
        message: String,
    },
    /// The scene parsed but is not a valid world (a copter outside the arena, a duplicate
    /// name, a non-finite value, ...).
    #[error("{origin}:{}: {path}: {message}", fmt_loc(.location))]
    Invalid {
        /// File name or other origin of the text.
        origin: String,
        /// Where, if known.
        location: Option<Location>,
        /// The field at fault.
        path: FieldPath,
        /// What is wrong.
        message: String,
    },
}

fn fmt_loc(loc: &Option<Location>) -> String {
    match loc {
        Some(l) => format!("{}:{}", l.line, l.column),
        None => "?:?".into(),
    }
}

impl SceneError {
    /// The field path the error names.
    pub fn path(&self) -> &FieldPath {
        match self {
            SceneError::Syntax { path, .. } | SceneError::Invalid { path, .. } => path,
        }
    }
    /// The bare message, without origin and location.
    pub fn message(&self) -> &str {
        match self {
            SceneError::Syntax { message, .. } | SceneError::Invalid { message, .. } => message,
        }
    }
    /// The location, if known.
    pub fn location(&self) -> Option<Location> {
        match self {
            SceneError::Syntax { location, .. } | SceneError::Invalid { location, .. } => *location,
        }
    }
    pub(crate) fn invalid(path: FieldPath, message: impl Into<String>) -> Self {
        SceneError::Invalid { origin: String::new(), location: None, path, message: message.into() }
    }
}

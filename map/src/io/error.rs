//! The readers' errors: which format failed to parse and why ([`ParseError`]), and a file
//! that could not be read at all ([`ReadError`]).

use std::path::PathBuf;

/// Which reader failed.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Format {
    Pcd,
    Ply,
    /// KITTI `.bin` scans: float32 x y z intensity.
    KittiBin,
    /// KITTI odometry or TUM pose lines.
    Poses,
}

impl std::fmt::Display for Format {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Self::Pcd => "PCD",
            Self::Ply => "PLY",
            Self::KittiBin => "KITTI .bin",
            Self::Poses => "pose file",
        })
    }
}

/// Bytes that are not a valid file of `format`: what is wrong, with where (a header
/// line, a vertex, a line number) where the reader knows it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ParseError {
    pub format: Format,
    pub problem: String,
}

impl ParseError {
    pub(crate) fn new(format: Format) -> impl Fn(String) -> Self {
        move |problem| Self { format, problem }
    }
}

impl std::fmt::Display for ParseError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "bad {}: {}", self.format, self.problem)
    }
}

impl std::error::Error for ParseError {}

/// A file could not be read or parsed; names the file.
#[derive(Debug)]
pub struct ReadError {
    pub path: PathBuf,
    pub kind: ReadErrorKind,
}

/// What went wrong with a [`ReadError`]'s file.
#[derive(Debug)]
pub enum ReadErrorKind {
    Io(std::io::Error),
    Parse(ParseError),
}

/// Names the file only: what went wrong is the [`std::error::Error::source`], so that an
/// error chain (`{:#}` in anyhow) says it once.
impl std::fmt::Display for ReadError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match &self.kind {
            ReadErrorKind::Io(_) => write!(f, "{}: cannot read", self.path.display()),
            ReadErrorKind::Parse(_) => write!(f, "{}", self.path.display()),
        }
    }
}

impl std::error::Error for ReadError {
    fn source(&self) -> Option<&(dyn std::error::Error + 'static)> {
        match &self.kind {
            ReadErrorKind::Io(e) => Some(e),
            ReadErrorKind::Parse(e) => Some(e),
        }
    }
}

//! Typed errors of the library. Every error names the file and the node or key at
//! fault; only the binary turns them into messages and exit codes (STYLE.md §8).

use std::path::{Path, PathBuf};

/// Everything that can go wrong between reading a job and writing its frames.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// The input (job file, scene file, command line) is wrong: exit code 2.
    #[error("{}: {at}: {message}", file.display())]
    Input {
        file: PathBuf,
        /// The node, key or element at fault, e.g. `nodes[3] "Wheel"` or `frames.end`.
        at: String,
        message: String,
    },
    /// The output location cannot be used (checked before any frame renders): exit code 2.
    #[error("{}: {message}", path.display())]
    Output { path: PathBuf, message: String },
    /// Rendering or writing a frame failed after the input was accepted: exit code 1.
    #[error("render failed: {0}")]
    Render(String),
}

impl Error {
    pub fn input(
        file: impl AsRef<Path>,
        at: impl Into<String>,
        message: impl Into<String>,
    ) -> Self {
        Error::Input {
            file: file.as_ref().to_path_buf(),
            at: at.into(),
            message: message.into(),
        }
    }

    /// Process exit code for this error: 2 for bad input, 1 for render failures.
    pub fn exit_code(&self) -> i32 {
        match self {
            Error::Input { .. } | Error::Output { .. } => 2,
            Error::Render(_) => 1,
        }
    }
}

pub type Result<T, E = Error> = std::result::Result<T, E>;

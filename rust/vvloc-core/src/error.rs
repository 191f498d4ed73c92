//! The one error type of the core crate. The Python bindings map it to `ValueError`/`TypeError`.

/// Errors raised by vvloc-core on invalid input. Kernels never panic on user input.
#[derive(Debug, thiserror::Error, Clone, PartialEq)]
pub enum Error {
    /// An argument has the wrong shape; `arg` names it, `expected` says what was required.
    #[error("{arg}: expected shape {expected}, got {got}")]
    Shape {
        arg: &'static str,
        expected: String,
        got: String,
    },
    /// An argument has an invalid value (non-finite, out of range, inconsistent).
    #[error("{arg}: {msg}")]
    Value { arg: &'static str, msg: String },
    /// A stored file (index, map) is malformed, truncated or from another version.
    #[error("{0}")]
    Format(String),
    /// An I/O failure, with the path it concerns.
    #[error("{path}: {msg}")]
    Io { path: String, msg: String },
}

/// Result alias of the core crate.
pub type Result<T> = std::result::Result<T, Error>;

impl Error {
    /// Convenience constructor for [`Error::Value`].
    pub fn value(arg: &'static str, msg: impl Into<String>) -> Self {
        Error::Value {
            arg,
            msg: msg.into(),
        }
    }

    /// Convenience constructor for [`Error::Shape`].
    pub fn shape(
        arg: &'static str,
        expected: impl Into<String>,
        got: impl std::fmt::Debug,
    ) -> Self {
        Error::Shape {
            arg,
            expected: expected.into(),
            got: format!("{got:?}"),
        }
    }
}

//! Typed errors of the library. Each variant knows whether it is bad input (exit 2) or an
//! internal failure (exit 1); the binary maps them with [`Error::exit_code`].

use std::path::PathBuf;

/// Everything that can go wrong inside `sisfilt`.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// A config value is invalid; `key` is the TOML key path (e.g. `model.B`).
    #[error("{file}: {key}: {msg}")]
    Config {
        file: String,
        key: String,
        msg: String,
    },

    /// The TOML could not be parsed (syntax, type, unknown or missing key).
    #[error("{file}: line {line}: {msg}")]
    ConfigSyntax {
        file: String,
        line: usize,
        msg: String,
    },

    /// A CSV file is malformed; `line` is 1-based and counts the header.
    #[error("{file}: line {line}: {msg}")]
    Csv {
        file: String,
        line: u64,
        msg: String,
    },

    /// A JSON file is malformed, or not the document expected; `line` is 1-based.
    #[error("{file}: line {line}: {msg}")]
    Json {
        file: String,
        line: usize,
        msg: String,
    },

    /// An input file as a whole is unusable (missing rows at the end, wrong size).
    #[error("{file}: {msg}")]
    File { file: String, msg: String },

    /// The settings of a run do not go together ([`crate::run::RunSpec::check`]).
    #[error(transparent)]
    Spec(#[from] crate::run::SpecError),

    /// The settings of an evaluation cannot serve ([`crate::evaluate::EvaluateError`]).
    #[error(transparent)]
    Evaluate(#[from] crate::evaluate::EvaluateError),

    /// Parts that do not add up to one study ([`crate::evaluate::MergeError`]).
    #[error(transparent)]
    Merge(#[from] crate::evaluate::MergeError),

    /// A run cannot go on for a reason its settings name ([`crate::run::RunError`]).
    #[error(transparent)]
    Run(#[from] crate::run::RunError),

    /// Settings of a fit that do not go together (docs/theory.md §16).
    #[error(transparent)]
    Fit(#[from] crate::fit::FitError),

    /// A command-line argument is unusable.
    #[error("{0}")]
    Usage(String),

    /// The interconnection equations (docs/theory.md §2) of a config have no unique solution at `t`.
    #[error("{file}: interconnection system at t = {t} is not well posed: {msg}")]
    IllPosed { file: String, t: usize, msg: String },

    /// The paper's transfer solver (docs/theory.md §2) cannot run on a chain where the banded
    /// solve can: an interior subsystem's `G22` is singular.
    #[error(
        "{file}: the transfer solver cannot run at t = {t}: it needs G22 of every interior subsystem invertible, but G22 of subsystem {subsystem} is singular (the banded solver needs no such inverse)"
    )]
    TransferSolver {
        file: String,
        t: usize,
        subsystem: usize,
    },

    /// Reading or writing a file failed. (`err` is not a `#[source]`: the message already
    /// says it, and `{:#}` would print it twice.)
    #[error("{}: {err}", path.display())]
    Io { path: PathBuf, err: std::io::Error },

    /// An input the user named cannot be opened or read, whatever the system's reason (it is
    /// missing, a folder, a socket, a loop of links, a name too long): bad input, unless the
    /// machine itself failed (out of memory, interrupted).
    #[error("{}: {err}", path.display())]
    Read { path: PathBuf, err: std::io::Error },

    /// The numerics broke down on a valid config (e.g. an innovation covariance that is not
    /// positive definite).
    #[error("t = {t}, i = {i}: {msg}")]
    Numerical { t: usize, i: usize, msg: String },

    /// An array the run would allocate is larger than `max_memory` allows ([`crate::memory`]):
    /// bad input, since a setting asked for it.
    #[error(
        "{what} needs {} ({need} bytes), above max_memory {} ({limit} bytes); raise max_memory",
        crate::memory::human_bytes(*need),
        crate::memory::human_bytes(*limit)
    )]
    OverMemory { what: String, need: u64, limit: u64 },

    /// An error in run `run` (1-based) of a Monte Carlo study.
    #[error("run {run}, {error}")]
    InRun { run: usize, error: Box<Error> },

    /// The caller asked the run to stop (a front end's interrupt, e.g. Ctrl-C in Python).
    #[error("interrupted")]
    Interrupted,
}

impl Error {
    /// 2 for bad input (config, CSV, arguments), 1 for internal failure (docs/theory.md §13).
    pub fn exit_code(&self) -> u8 {
        match self {
            Error::Numerical { .. } => 1,
            Error::InRun { error, .. } => error.exit_code(),
            Error::Read { err, .. } => match err.kind() {
                std::io::ErrorKind::OutOfMemory | std::io::ErrorKind::Interrupted => 1,
                _ => 2,
            },
            Error::Io { err: source, .. } if source.kind() != std::io::ErrorKind::NotFound => {
                if matches!(
                    source.kind(),
                    std::io::ErrorKind::PermissionDenied
                        | std::io::ErrorKind::NotADirectory
                        | std::io::ErrorKind::IsADirectory
                        | std::io::ErrorKind::AlreadyExists
                        | std::io::ErrorKind::InvalidInput
                        | std::io::ErrorKind::InvalidData
                        | std::io::ErrorKind::ReadOnlyFilesystem
                ) {
                    2
                } else {
                    1
                }
            }
            _ => 2,
        }
    }

    /// `Ok` when every value is finite; else the breakdown at step `t` (1-based) in the first
    /// subsystem whose block of `width` values holds one that is not: overflow or NaN must
    /// stop a run, never reach an output.
    pub fn check_finite(
        t: usize,
        width: usize,
        values: &[f64],
        msg: impl FnOnce() -> String,
    ) -> Result<()> {
        match crate::linalg::first_non_finite_block(values, width) {
            None => Ok(()),
            Some(i) => Err(Error::Numerical {
                t,
                i: i + 1,
                msg: msg(),
            }),
        }
    }

    /// `file` is not `expected` (e.g. "a run record written by `sisfilt simulate`"): the
    /// parser's error `e`, at its line.
    pub fn json(file: impl Into<String>, expected: &str, e: &serde_json::Error) -> Self {
        Error::Json {
            file: file.into(),
            line: e.line(),
            msg: format!(
                "not {expected}: {}",
                crate::messages::parser_message(&e.to_string())
            ),
        }
    }

    /// A failed open or read of the input `path` the user named ([`Error::Read`]).
    pub fn read(path: impl Into<PathBuf>, source: std::io::Error) -> Self {
        Error::Read {
            path: path.into(),
            err: source,
        }
    }

    /// A failed read or write of `path`.
    pub fn io(path: impl Into<PathBuf>, source: std::io::Error) -> Self {
        Error::Io {
            path: path.into(),
            err: source,
        }
    }
}

/// Result with the library's [`Error`].
pub type Result<T, E = Error> = std::result::Result<T, E>;

#[cfg(test)]
mod tests {
    use super::*;

    /// The first subsystem holding a value that is not finite is named, 1-based; in a Monte
    /// Carlo study the run too; a breakdown is an internal failure (exit 1).
    #[test]
    fn a_breakdown_names_t_i_and_the_run() {
        let values = [0.0, 1.0, 2.0, f64::NAN, 4.0, f64::INFINITY];
        let err = Error::check_finite(7, 2, &values, || "overflow".into()).unwrap_err();
        assert_eq!(err.to_string(), "t = 7, i = 2: overflow");
        let in_run = Error::InRun {
            run: 3,
            error: Box::new(err),
        };
        assert_eq!(in_run.to_string(), "run 3, t = 7, i = 2: overflow");
        assert_eq!(in_run.exit_code(), 1);
        assert!(Error::check_finite(1, 2, &[1.0, 2.0, -3.0], || panic!("all finite")).is_ok());
    }
}

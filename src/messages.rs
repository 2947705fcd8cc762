//! Messages on standard error (docs/theory.md §13), in one format: `error: …`, `warning: …`, reports such
//! as `accuracy: …` and, with `--verbose`, `info: …` — each exactly one line. Standard output
//! carries only data.
//!
//! The verbosity is process-wide, set once by the binary from `--quiet` / `--verbose`:
//! `--quiet` drops warnings, notes and progress bars (errors are always printed);
//! `--verbose` adds progress and timing lines.

use std::fmt::Display;
use std::io::Write;
use std::sync::atomic::{AtomicU8, Ordering};

/// How much `sisfilt` says on standard error besides errors.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub enum Verbosity {
    /// Errors only.
    Quiet = 0,
    /// Errors, warnings and the reports a command was asked for (the default).
    Normal = 1,
    /// Also progress and timings.
    Verbose = 2,
}

static LEVEL: AtomicU8 = AtomicU8::new(Verbosity::Normal as u8);

/// Sets the verbosity of the whole process.
pub fn set_verbosity(v: Verbosity) {
    LEVEL.store(v as u8, Ordering::Relaxed);
}

/// The verbosity of the process.
pub fn verbosity() -> Verbosity {
    match LEVEL.load(Ordering::Relaxed) {
        0 => Verbosity::Quiet,
        1 => Verbosity::Normal,
        _ => Verbosity::Verbose,
    }
}

/// `msg` as one line: any line breaks inside become `; `, so that a message can never break
/// the one-line-per-message format that scripts parse.
pub fn one_line(msg: impl Display) -> String {
    let text = msg.to_string();
    let mut out = String::with_capacity(text.len());
    for part in text.lines().map(str::trim).filter(|l| !l.is_empty()) {
        if !out.is_empty() {
            out.push_str("; ");
        }
        out.push_str(part);
    }
    out
}

/// Prints `error: {msg}` (always).
pub fn error(msg: impl Display) {
    let _ = writeln!(std::io::stderr(), "error: {}", one_line(msg));
}

/// Prints `warning: {msg}` unless `--quiet`.
pub fn warn(msg: impl Display) {
    if verbosity() >= Verbosity::Normal {
        let _ = writeln!(std::io::stderr(), "warning: {}", one_line(msg));
    }
}

/// Prints `{kind}: {msg}`: a report the command was asked for (e.g. `accuracy: …` for
/// `estimate --truth`); always, since it is output rather than commentary.
pub fn report(kind: &str, msg: impl Display) {
    let _ = writeln!(std::io::stderr(), "{kind}: {}", one_line(msg));
}

/// Prints `{kind}: {msg}` unless `--quiet`: a figure the command gives on its own (the
/// innovation check of `estimate`, docs/theory.md §14).
pub fn finding(kind: &str, msg: impl Display) {
    if verbosity() >= Verbosity::Normal {
        let _ = writeln!(std::io::stderr(), "{kind}: {}", one_line(msg));
    }
}

/// Prints `info: {msg}` with `--verbose` only (progress, timings, files written).
pub fn info(msg: impl Display) {
    if verbosity() >= Verbosity::Verbose {
        let _ = writeln!(std::io::stderr(), "info: {}", one_line(msg));
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn line_breaks_are_joined() {
        assert_eq!(one_line("a\n  b\n\nc "), "a; b; c");
        assert_eq!(one_line("single"), "single");
    }
}

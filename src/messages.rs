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

/// `text` as a message quotes a cell or a value: escaped (a line break shows as `\n`), and if
/// longer than forty characters, its first forty, `…` and its length in bytes, so that a
/// message about a 10 MB cell stays one short line.
pub fn excerpt(text: &str) -> String {
    shortened(text, 40)
}

/// `text` as a message quotes a line (a header): as [`excerpt`], with two hundred characters.
pub fn line_excerpt(text: &str) -> String {
    shortened(text, 200)
}

fn shortened(text: &str, chars: usize) -> String {
    match text.char_indices().nth(chars) {
        None => text.escape_debug().to_string(),
        Some((end, _)) => format!("{}… ({} bytes)", text[..end].escape_debug(), text.len()),
    }
}

/// A parser's message (TOML, serde) as one line, each span quoted in it (`…` or \"…\")
/// longer than forty characters cut as [`excerpt`] cuts (serde quotes the whole of an unknown
/// or mistyped value, however long), and the whole at most a thousand characters.
pub fn parser_message(msg: &str) -> String {
    let mut line = msg.trim().replace('\n', " ");
    for quote in ['`', '"'] {
        let mut out = String::with_capacity(line.len().min(1000));
        for (k, part) in line.split(quote).enumerate() {
            if k > 0 {
                out.push(quote);
            }
            match part.char_indices().nth(40) {
                Some((end, _)) if k % 2 == 1 => {
                    out += &format!("{}… ({} bytes)", &part[..end], part.len());
                }
                _ => out.push_str(part),
            }
        }
        line = out;
    }
    match line.char_indices().nth(1000) {
        Some((end, _)) => format!("{}…", &line[..end]),
        None => line,
    }
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

    #[test]
    fn an_excerpt_is_short_whatever_it_quotes() {
        assert_eq!(excerpt("1.5e"), "1.5e");
        assert_eq!(excerpt("a\nb"), "a\\nb");
        let forty = "x".repeat(40);
        assert_eq!(excerpt(&forty), forty);
        let cell = format!("{}{}", "é".repeat(41), "y".repeat(10_000_000));
        assert_eq!(
            excerpt(&cell),
            format!("{}… (10000082 bytes)", "é".repeat(40))
        );
        assert_eq!(
            line_excerpt(&cell).chars().count(),
            200 + "… (10000082 bytes)".chars().count()
        );
        let serde = format!(
            "unknown variant `{}`, expected `sine` or\n `file`",
            "s".repeat(100)
        );
        assert_eq!(
            parser_message(&serde),
            format!(
                "unknown variant `{}… (100 bytes)`, expected `sine` or  `file`",
                "s".repeat(40)
            )
        );
    }
}

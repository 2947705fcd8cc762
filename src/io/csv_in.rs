//! Streaming reader for the per-`(t, i)` CSV files of docs/theory.md §13 (measurements, inputs, truth).
//! It hands out one time step at a time, so memory does not grow with `T`, and checks the
//! header, the row order (`t` then `i`), completeness and every number, naming the file and line.

use std::io::Read;

use crate::error::{Error, Result};
use crate::messages::{excerpt, line_excerpt};

/// The longest line a CSV file may have: far beyond any row of the files of docs/theory.md
/// §13 (an estimates row of the joint filter with a band of a thousand holds a few hundred
/// KB), and a bound on what a line without end (`/dev/zero`) makes the reader hold.
pub const MAX_LINE_BYTES: usize = 16 << 20;

/// A reader that fails once a line grows past [`MAX_LINE_BYTES`], before the CSV parser has
/// buffered it whole.
pub struct LineLimit<R> {
    inner: R,
    /// Bytes since the last line break.
    since_break: usize,
}

/// The error [`LineLimit`] returns, found again by [`StepReader`] to name the line.
#[derive(Debug)]
struct LineTooLong;

impl std::fmt::Display for LineTooLong {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "a line longer than {} (the longest a file may have)",
            crate::memory::human_bytes(MAX_LINE_BYTES as u64)
        )
    }
}

impl std::error::Error for LineTooLong {}

impl<R> LineLimit<R> {
    pub fn new(inner: R) -> Self {
        Self {
            inner,
            since_break: 0,
        }
    }
}

impl<R: Read> Read for LineLimit<R> {
    fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
        let n = self.inner.read(buf)?;
        let chunk = &buf[..n];
        // Both searches stop at the first line break they meet: cheap for short lines.
        match chunk.iter().position(|&b| b == b'\n') {
            None => self.since_break += n,
            Some(first) => {
                self.since_break += first;
                if self.since_break <= MAX_LINE_BYTES {
                    let last = chunk.iter().rposition(|&b| b == b'\n').unwrap_or(first);
                    self.since_break = n - 1 - last;
                }
            }
        }
        if self.since_break > MAX_LINE_BYTES {
            return Err(std::io::Error::new(
                std::io::ErrorKind::InvalidData,
                LineTooLong,
            ));
        }
        Ok(n)
    }
}

/// What a file's columns must be: `t,i,{prefix}1..{prefix}width` and then `extra` columns.
#[derive(Debug, Clone)]
pub struct StepLayout {
    /// Name of the value columns without their index (`y`, `u`, `x`).
    pub prefix: &'static str,
    /// Number of indexed value columns.
    pub width: usize,
    /// Columns after the indexed ones (`gamma` in the truth file).
    pub extra: &'static [&'static str],
    /// Whether an empty cell is allowed (read as NaN: a lost measurement element).
    pub allow_empty: bool,
}

impl StepLayout {
    /// The measurement file: `t,i,y1..yq`. An empty cell is an element not in the data (a
    /// gap, or a lost element with known dropouts; docs/theory.md §15).
    pub fn measurements(q: usize) -> Self {
        Self {
            prefix: "y",
            width: q,
            extra: &[],
            allow_empty: true,
        }
    }

    /// The inputs file: `t,i,u1..um`.
    pub fn inputs(m: usize) -> Self {
        Self {
            prefix: "u",
            width: m,
            extra: &[],
            allow_empty: false,
        }
    }

    /// The truth file: `t,i,x1..xn,gamma`, the states and whether the measurement arrived.
    pub fn truth(n: usize) -> Self {
        Self {
            prefix: "x",
            width: n,
            extra: &["gamma"],
            allow_empty: false,
        }
    }

    /// The same layout with `width` value columns (a file whose width is read from its
    /// header).
    pub fn with_width(self, width: usize) -> Self {
        Self { width, ..self }
    }

    /// The header the file must have.
    pub fn header(&self) -> Vec<String> {
        let mut h = vec!["t".to_string(), "i".to_string()];
        h.extend((1..=self.width).map(|k| format!("{}{k}", self.prefix)));
        h.extend(self.extra.iter().map(|s| s.to_string()));
        h
    }
}

/// A plain decimal integer (what `usize::from_str` accepts, without its allocation-free but
/// slower UTF-8 round trip); `None` when empty, not all digits, or too large.
#[inline]
fn parse_plain_index(bytes: &[u8]) -> Option<usize> {
    let digits = bytes.strip_prefix(b"+").unwrap_or(bytes);
    if digits.is_empty() {
        return None;
    }
    let mut value: usize = 0;
    for &b in digits {
        let d = b.wrapping_sub(b'0');
        if d > 9 {
            return None;
        }
        value = value.checked_mul(10)?.checked_add(d as usize)?;
    }
    Some(value)
}

/// An index `t` or `i`: a plain decimal integer, or a number with an integral value as numpy
/// and pandas write integers held in floats (`1.0`, `1.000000000000000000e+00`).
#[inline]
fn parse_index(bytes: &[u8]) -> Option<usize> {
    parse_plain_index(bytes).or_else(|| {
        let value: f64 = std::str::from_utf8(bytes).ok()?.parse().ok()?;
        // Below 2⁵³ every integer is exact in f64.
        let integral = value.fract() == 0.0 && (0.0..9.007_199_254_740_992e15).contains(&value);
        integral.then_some(value as usize)
    })
}

/// Whether a cell's text is a missing value as numpy (`nan`) and pandas (`NaN`) write one.
fn is_nan_text(text: &str) -> bool {
    text.eq_ignore_ascii_case("nan")
}

/// The cells of a header row, trimmed, without the `# ` that `numpy.savetxt` puts before its
/// header line.
pub fn header_cells<'a>(cells: impl Iterator<Item = &'a [u8]>) -> Vec<String> {
    let mut out: Vec<String> = cells
        .map(|f| String::from_utf8_lossy(f).trim().to_string())
        .collect();
    if let Some(first) = out.first_mut()
        && let Some(rest) = first.strip_prefix('#')
    {
        *first = rest.trim_start().to_string();
    }
    out
}

/// What a header that is not the expected one most likely means, for the message: a
/// DataFrame's index written before `t` (`to_csv` without `index=False`), or columns separated
/// by spaces (`numpy.savetxt` without `delimiter=","`).
fn header_hint(found: &[String], expected: &[String]) -> &'static str {
    if found.len() == expected.len() + 1 && found[1..] == *expected {
        " (a leading index column: a pandas DataFrame written without index=False?)"
    } else if found.len() == 1 && found[0].split_whitespace().count() > 1 {
        " (columns separated by spaces: numpy.savetxt writes commas with delimiter=\",\")"
    } else {
        ""
    }
}

/// Trailing columns that hold an indicator, 0 or 1: whether the measurement arrived.
const INDICATOR_COLUMNS: &[&str] = &["gamma"];

/// Reads a `t,i,…` CSV one time step (all `N` subsystems) at a time.
pub struct StepReader<R: Read> {
    name: String,
    /// The exact header the file must have: `t`, `i`, then the value columns.
    header: Vec<String>,
    /// The first column (of the row, `t` and `i` included) whose cells may be empty.
    optional_from: usize,
    subsystems: usize,
    /// The first indicator column (`gamma`, docs/theory.md §13: 0 or 1); the header's length if none.
    first_indicator: usize,
    reader: csv::Reader<LineLimit<R>>,
    record: csv::ByteRecord,
    next_t: usize,
    last_line: u64,
}

impl<R: Read> StepReader<R> {
    /// Opens a reader and checks the header. `name` is used in messages.
    pub fn new(name: &str, source: R, layout: StepLayout, subsystems: usize) -> Result<Self> {
        Self::with_header(
            name,
            source,
            layout.header(),
            if layout.allow_empty { 0 } else { usize::MAX },
            subsystems,
        )
    }

    /// Like [`StepReader::new`], for files whose value columns are not `prefix1..prefixW`
    /// (the estimates file, docs/theory.md §13): `header` is the exact header, the step (`t`,
    /// or `t_given` for predicted estimates) and `i` first;
    /// a cell of value column `optional_from` (0-based, after `t` and `i`) or later may be empty.
    pub fn with_header(
        name: &str,
        source: R,
        header: Vec<String>,
        optional_from: usize,
        subsystems: usize,
    ) -> Result<Self> {
        debug_assert!(header.len() >= 2 && header[1] == "i");
        let reader = csv::ReaderBuilder::new()
            .has_headers(false)
            .flexible(true)
            .buffer_capacity(1 << 16)
            .from_reader(LineLimit::new(source));
        let first_indicator = header
            .iter()
            .position(|h| INDICATOR_COLUMNS.contains(&h.as_str()))
            .unwrap_or(header.len());
        let mut this = Self {
            name: name.to_string(),
            header,
            first_indicator,
            optional_from: optional_from.saturating_add(2),
            subsystems,
            reader,
            record: csv::ByteRecord::new(),
            next_t: 1,
            last_line: 1,
        };
        let expected = this.header.join(",");
        let got = this
            .reader
            .read_byte_record(&mut this.record)
            .map_err(|e| this.csv_error(1, e))?;
        if !got {
            return Err(this.err(1, format!("empty file; expected the header `{expected}`")));
        }
        let found = header_cells(this.record.iter());
        if found != this.header {
            return Err(this.err(
                1,
                format!(
                    "expected the header `{expected}`, found `{}`{}",
                    line_excerpt(&found.join(",")),
                    header_hint(&found, &this.header)
                ),
            ));
        }
        Ok(this)
    }

    fn err(&self, line: u64, msg: String) -> Error {
        Error::Csv {
            file: self.name.clone(),
            line,
            msg,
        }
    }

    fn csv_error(&self, line: u64, e: csv::Error) -> Error {
        match e.kind() {
            csv::ErrorKind::Io(io) if io.get_ref().is_some_and(|e| e.is::<LineTooLong>()) => {
                self.err(line, LineTooLong.to_string())
            }
            csv::ErrorKind::Io(io) => Error::Io {
                path: self.name.clone().into(),
                err: std::io::Error::new(io.kind(), io.to_string()),
            },
            _ => {
                let line = e.position().map_or(line, |p| p.line());
                self.err(line, e.to_string())
            }
        }
    }

    /// The file name used in messages.
    pub fn name(&self) -> &str {
        &self.name
    }

    /// The chain length `N`: the rows of one time step.
    pub fn subsystems(&self) -> usize {
        self.subsystems
    }

    /// The number of values [`StepReader::read_step`] fills per time step.
    pub fn row_values(&self) -> usize {
        self.subsystems * (self.header.len() - 2)
    }

    /// The next time step this reader expects (1-based).
    pub fn next_t(&self) -> usize {
        self.next_t
    }

    /// Reads the rows of the next time step into `out` (`N · (width + extra)` values, row by
    /// row; an empty cell reads as NaN). Returns the step read, or `None` at the end of file.
    pub fn read_step(&mut self, out: &mut [f64]) -> Result<Option<usize>> {
        let t = self.next_t;
        let per_row = self.header.len() - 2;
        debug_assert_eq!(out.len(), self.subsystems * per_row);
        for i in 1..=self.subsystems {
            let more = self
                .reader
                .read_byte_record(&mut self.record)
                .map_err(|e| self.csv_error(self.last_line + 1, e))?;
            if !more {
                if i == 1 {
                    return Ok(None);
                }
                return Err(self.err(
                    self.last_line + 1,
                    format!(
                        "file ends inside time step t = {t}: expected rows for i = {i}..{}",
                        self.subsystems
                    ),
                ));
            }
            let line = self
                .record
                .position()
                .map_or(self.last_line + 1, |p| p.line());
            self.last_line = line;
            if self.record.len() != self.header.len() {
                return Err(self.err(
                    line,
                    format!(
                        "expected {} columns ({}), found {}",
                        self.header.len(),
                        self.header.join(","),
                        self.record.len()
                    ),
                ));
            }
            let (rt, ri) = (self.index(line, 0)?, self.index(line, 1)?);
            if (rt, ri) != (t, i) {
                return Err(self.err(
                    line,
                    format!(
                        "expected the row t = {t}, i = {i}, found t = {rt}, i = {ri} \
                         (rows are ordered by t then i, with i = 1..{} for every t)",
                        self.subsystems
                    ),
                ));
            }
            for k in 0..per_row {
                out[(i - 1) * per_row + k] = self.number(line, 2 + k)?;
            }
            for col in self.first_indicator..self.header.len() {
                let v = out[(i - 1) * per_row + col - 2];
                if v != 0.0 && v != 1.0 {
                    return Err(self.err(
                        line,
                        format!(
                            "column `{}`: expected 0 (lost) or 1 (received), found `{}`",
                            self.column_name(col),
                            excerpt(
                                String::from_utf8_lossy(self.record.get(col).unwrap_or_default())
                                    .trim()
                            )
                        ),
                    ));
                }
            }
        }
        self.next_t += 1;
        Ok(Some(t))
    }

    fn column_name(&self, col: usize) -> String {
        self.header[col].clone()
    }

    fn index(&self, line: u64, col: usize) -> Result<usize> {
        let field = self.record.get(col).unwrap_or_default();
        parse_index(field.trim_ascii()).ok_or_else(|| {
            self.err(
                line,
                format!(
                    "column `{}`: expected a positive integer, found `{}`",
                    self.column_name(col),
                    excerpt(&String::from_utf8_lossy(field))
                ),
            )
        })
    }

    fn number(&self, line: u64, col: usize) -> Result<f64> {
        let field = self.record.get(col).unwrap_or_default();
        let Ok(text) = std::str::from_utf8(field.trim_ascii()) else {
            return Err(self.err(
                line,
                format!(
                    "column `{}`: expected a finite number, found `{}` (not UTF-8)",
                    self.column_name(col),
                    excerpt(&String::from_utf8_lossy(field))
                ),
            ));
        };
        // A missing value where one may be missing; elsewhere `NaN` is refused below, as
        // any number that is not finite.
        if (text.is_empty() || is_nan_text(text)) && col >= self.optional_from {
            return Ok(f64::NAN);
        }
        if text.is_empty() {
            return Err(self.err(
                line,
                format!("column `{}`: empty cell", self.column_name(col)),
            ));
        }
        match text.parse::<f64>() {
            Ok(v) if v.is_finite() => Ok(v),
            _ => Err(self.err(
                line,
                format!(
                    "column `{}`: expected a finite number, found `{}`",
                    self.column_name(col),
                    excerpt(&String::from_utf8_lossy(field))
                ),
            )),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::{header_cells, parse_index, parse_plain_index};

    #[test]
    fn index_parsing_matches_the_standard_library() {
        for text in [
            "0",
            "1",
            "+7",
            "0012",
            "18446744073709551615",
            "18446744073709551616",
            "",
            "+",
            "-1",
            "1.0",
            "1e3",
            " 1",
            "x",
            "99999999999999999999",
        ] {
            assert_eq!(
                parse_plain_index(text.as_bytes()),
                text.parse::<usize>().ok(),
                "{text:?}"
            );
        }
    }

    /// numpy and pandas write integers held in floats as `1.0` or `1.000000000000000000e+00`:
    /// read as the integer; anything with a fraction, negative or beyond 2⁵³ is not an index.
    #[test]
    fn indices_written_as_floats_are_read_when_integral() {
        for (text, want) in [
            ("12", Some(12)),
            ("1.0", Some(1)),
            ("1.000000000000000000e+00", Some(1)),
            ("2.5e1", Some(25)),
            ("1e3", Some(1000)),
            ("1.5", None),
            ("-1.0", None),
            ("nan", None),
            ("inf", None),
            ("1e300", None),
            ("", None),
        ] {
            assert_eq!(parse_index(text.as_bytes()), want, "{text:?}");
        }
    }

    #[test]
    fn a_numpy_header_loses_its_comment_mark() {
        let cells = |line: &'static str| header_cells(line.split(',').map(str::as_bytes));
        assert_eq!(cells("# t,i,y1"), ["t", "i", "y1"]);
        assert_eq!(cells("#t, i ,y1"), ["t", "i", "y1"]);
        assert_eq!(cells("t,i,y1"), ["t", "i", "y1"]);
    }
}

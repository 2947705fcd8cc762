//! Reading the files the figures are drawn from (docs/theory.md §13): truth, estimates (CSV or the JSON of
//! `estimate --format json`) and measurements. The chain length `N` and the widths are learnt
//! from the files themselves; the rows are then read and checked by the streaming
//! [`StepReader`], one time step at a time, so that only what a figure needs is kept.

use std::fs::File;
use std::io::{BufReader, Read};
use std::path::Path;
use std::sync::OnceLock;

use crate::error::{Error, Result};
use crate::io::estimates::{EstimatesColumns, EstimatesDocument};
use crate::io::{LineLimit, MAX_DOCUMENT_BYTES, StepLayout, StepReader, read_bytes};

/// The streaming reader of a per-`(t, i)` CSV file.
type CsvReader = StepReader<Box<dyn Read>>;

/// A file's name as used in messages (`<stdin>` for `-`).
pub(crate) fn display_name(path: &Path) -> String {
    if is_stdin(path) {
        "<stdin>".into()
    } else {
        path.display().to_string()
    }
}

/// A file's name for a figure's title: its last component, or `standard input` for `-`.
pub(crate) fn file_name(path: &Path) -> String {
    if is_stdin(path) {
        return "standard input".into();
    }
    path.file_name().map_or_else(
        || path.display().to_string(),
        |f| f.to_string_lossy().into(),
    )
}

fn is_stdin(path: &Path) -> bool {
    path.as_os_str() == "-"
}

/// Opens a file the figures are drawn from; `-` is standard input, read once and kept, since
/// a figure reads its files twice (the shape, then the rows) and only one of them can be
/// standard input (`check_files`).
pub(crate) fn open(path: &Path) -> Result<Box<dyn Read>> {
    if !is_stdin(path) {
        return Ok(Box::new(BufReader::new(
            File::open(path).map_err(|e| Error::read(path, e))?,
        )));
    }
    static STDIN: OnceLock<Vec<u8>> = OnceLock::new();
    let bytes = match STDIN.get() {
        Some(bytes) => bytes,
        None => {
            // Held whole, so bounded as a document is.
            let bytes = read_bytes(
                "<stdin>",
                std::io::stdin().lock(),
                MAX_DOCUMENT_BYTES,
                "the most a figure holds of standard input; give the file by its name",
            )?;
            STDIN.get_or_init(|| bytes)
        }
    };
    Ok(Box::new(bytes.as_slice()))
}

/// Whether the estimates at `path` are JSON: by the name, or for standard input by the first
/// character that is not white space.
fn is_json(path: &Path) -> Result<bool> {
    if !is_stdin(path) {
        return Ok(path
            .extension()
            .is_some_and(|e| e.eq_ignore_ascii_case("json")));
    }
    let mut first = [0u8];
    let mut input = open(path)?;
    while input
        .read(&mut first)
        .map_err(|e| Error::read("<stdin>", e))?
        == 1
    {
        if !first[0].is_ascii_whitespace() {
            return Ok(first[0] == b'{');
        }
    }
    Ok(false)
}

/// The header and the chain length `N` of a per-`(t, i)` CSV: `N` is the number of rows of
/// its first time step. A malformed row stops the count; the [`StepReader`] then names it.
fn probe_csv(path: &Path) -> Result<(Vec<String>, usize)> {
    let name = display_name(path);
    let mut reader = csv::ReaderBuilder::new()
        .has_headers(false)
        .flexible(true)
        .from_reader(LineLimit::new(open(path)?));
    let mut record = csv::StringRecord::new();
    let csv_err = |e: csv::Error| Error::Csv {
        file: name.clone(),
        line: e.position().map_or(1, |p| p.line()),
        msg: e.to_string(),
    };
    if !reader.read_record(&mut record).map_err(csv_err)? {
        return Err(Error::Csv {
            file: name,
            line: 1,
            msg: "empty file; expected a header row".into(),
        });
    }
    let header = crate::io::csv_in::header_cells(record.as_byte_record().iter());
    let mut first_t: Option<String> = None;
    let mut subsystems = 0;
    while reader.read_record(&mut record).map_err(csv_err)? {
        let t = record.get(0).unwrap_or_default().trim().to_string();
        match &first_t {
            None => first_t = Some(t),
            Some(f) if *f != t => break,
            Some(_) => {}
        }
        subsystems += 1;
    }
    if subsystems == 0 {
        return Err(Error::File {
            file: name,
            msg: "holds no rows after the header".into(),
        });
    }
    Ok((header, subsystems))
}

/// The 0-based index of the 1-based `value` of the command-line option `option`, which must
/// lie in `1..=count`; `holds` says where `count` comes from, for the message.
pub fn one_based(option: &str, value: usize, count: usize, holds: &str) -> Result<usize> {
    if !(1..=count).contains(&value) {
        return Err(Error::Usage(format!(
            "{option} {value}: expected 1..{count} ({holds})"
        )));
    }
    Ok(value - 1)
}

/// The truth file of `simulate`: `t,i,x1..xn,gamma`.
pub struct TruthFile {
    pub reader: CsvReader,
    /// State dimension `n`.
    pub n: usize,
    /// Chain length `N`.
    pub subsystems: usize,
}

/// A per-`(t, i)` CSV of `layout` (docs/theory.md §13), its width `w` learnt from the header:
/// the reader, `w` and the chain length `N`.
fn open_step_file(path: &Path, layout: StepLayout) -> Result<(CsvReader, usize, usize)> {
    let (header, subsystems) = probe_csv(path)?;
    let width = header.len().saturating_sub(2 + layout.extra.len()).max(1);
    let layout = layout.with_width(width);
    let reader = StepReader::new(&display_name(path), open(path)?, layout, subsystems)?;
    Ok((reader, width, subsystems))
}

impl TruthFile {
    pub fn open(path: &Path) -> Result<Self> {
        let (reader, n, subsystems) = open_step_file(path, StepLayout::truth(0))?;
        Ok(Self {
            reader,
            n,
            subsystems,
        })
    }

    /// Values per time step: `N (n + 1)` (the states, then `gamma`, per subsystem).
    pub fn row_values(&self) -> usize {
        self.subsystems * (self.n + 1)
    }
}

/// The measurement file: `t,i,y1..yq` (an empty cell, an element not in the data, reads as NaN).
pub struct MeasurementFile {
    pub reader: CsvReader,
    pub q: usize,
    pub subsystems: usize,
}

impl MeasurementFile {
    pub fn open(path: &Path) -> Result<Self> {
        let (reader, q, subsystems) = open_step_file(path, StepLayout::measurements(0))?;
        Ok(Self {
            reader,
            q,
            subsystems,
        })
    }
}

enum EstimatesSource {
    Csv(Box<StepReader<Box<dyn Read>>>),
    Json {
        rows: std::vec::IntoIter<Vec<Option<f64>>>,
        /// 1-based number of the next row, for messages.
        row_number: usize,
        next_t: usize,
    },
}

/// An estimates file (docs/theory.md §13): `t,i,x1..xn,P1_1,P1_2..Pn_n`, in JSON perhaps
/// with cross-covariance columns, perhaps with `arrival` last; as CSV or as the JSON of
/// `estimate --format json` (chosen by the extension `.json`).
pub struct EstimatesFile {
    source: EstimatesSource,
    name: String,
    columns: EstimatesColumns,
    /// State dimension `n`.
    pub n: usize,
    /// Chain length `N`.
    pub subsystems: usize,
}

impl EstimatesFile {
    pub fn open(path: &Path) -> Result<Self> {
        let name = display_name(path);
        let columns_of = |found: &[String]| {
            EstimatesColumns::parse(found).ok_or_else(|| Error::Csv {
                file: name.clone(),
                line: 1,
                msg: format!(
                    "expected the columns of an estimates file `t,i,x1..xn,P1_1,P1_2..Pn_n` (docs/theory.md §13), found `{}`",
                    crate::messages::line_excerpt(&found.join(","))
                ),
            })
        };
        if is_json(path)? {
            let doc: EstimatesDocument =
                serde_json::from_reader(open(path)?).map_err(|e| {
                    Error::json(
                        name.clone(),
                        "the JSON of `sisfilt estimate --format json` (expected its metadata, `columns` and `estimates`)",
                        &e,
                    )
                })?;
            let columns = columns_of(&doc.columns)?;
            let first_t = doc.estimates.first().and_then(|r| r.first().copied());
            let subsystems = doc
                .estimates
                .iter()
                .take_while(|r| r.first().copied() == first_t)
                .count();
            if subsystems == 0 {
                return Err(Error::File {
                    file: name,
                    msg: "holds no estimates".into(),
                });
            }
            return Ok(Self {
                source: EstimatesSource::Json {
                    rows: doc.estimates.into_iter(),
                    row_number: 1,
                    next_t: 1,
                },
                name,
                columns,
                n: columns.n,
                subsystems,
            });
        }
        let (header, subsystems) = probe_csv(path)?;
        let columns = columns_of(&header)?;
        // As in the JSON: estimates and covariances must be numbers; a cross-covariance
        // block, `π` or the NIS may be missing (empty).
        let own = columns.n + columns.n * (columns.n + 1) / 2;
        let reader = StepReader::with_header(&name, open(path)?, header, own, subsystems)?;
        Ok(Self {
            source: EstimatesSource::Csv(Box::new(reader)),
            name,
            columns,
            n: columns.n,
            subsystems,
        })
    }

    /// Refuses to score these estimates against a truth when they are predicted ones
    /// (`x̂(t+1|t)` on row `t`, which the first column, `t_given`, says).
    pub fn check_against_truth(&self) -> Result<()> {
        if !self.columns.predicted {
            return Ok(());
        }
        Err(Error::Usage(format!(
            "{}: predicted estimates (estimate --predicted: x̂(t+1|t) on row t_given = t) would be one step off against --truth; plot filtered or smoothed estimates, or leave --truth out",
            self.name
        )))
    }

    /// The file name used in messages.
    pub fn name(&self) -> &str {
        &self.name
    }

    /// Values per row: `n + n(n+1)/2`, the cross-covariance blocks, `arrival`.
    pub fn row_width(&self) -> usize {
        self.columns.values()
    }

    /// Where `π(t, i)` sits in a row, when the file has the `arrival` column (before `nis`).
    pub fn arrival_index(&self) -> Option<usize> {
        let after = usize::from(self.columns.nis);
        self.columns.arrival.then(|| self.row_width() - 1 - after)
    }

    /// Where the NIS of `(t, i)` sits in a row, when the file has the `nis` column (the last).
    pub fn nis_index(&self) -> Option<usize> {
        self.columns.nis.then(|| self.row_width() - 1)
    }

    /// Position of `P_kk` (0-based `k`) in a row of [`EstimatesFile::read_step`].
    pub fn variance_index(&self, k: usize) -> usize {
        variance_index(self.n, k)
    }

    /// Reads the next time step (`N` rows of [`EstimatesFile::row_width`] values) into `out`;
    /// `None` at the end of the file.
    pub fn read_step(&mut self, out: &mut [f64]) -> Result<Option<usize>> {
        let width = self.row_width();
        match &mut self.source {
            EstimatesSource::Csv(r) => r.read_step(out),
            EstimatesSource::Json {
                rows,
                row_number,
                next_t,
            } => {
                let t = *next_t;
                for i in 1..=self.subsystems {
                    let Some(row) = rows.next() else {
                        if i == 1 {
                            return Ok(None);
                        }
                        return Err(Error::File {
                            file: self.name.clone(),
                            msg: format!(
                                "estimates end inside time step t = {t}: expected rows for i = {i}..{}",
                                self.subsystems
                            ),
                        });
                    };
                    let bad = |msg: String| Error::File {
                        file: self.name.clone(),
                        msg: format!("estimates row {row_number}: {msg}"),
                    };
                    if row.len() != width + 2 {
                        return Err(bad(format!(
                            "expected {} numbers, found {}",
                            width + 2,
                            row.len()
                        )));
                    }
                    if (row[0], row[1]) != (Some(t as f64), Some(i as f64)) {
                        return Err(bad(format!(
                            "expected t = {t}, i = {i} (rows are ordered by t then i)"
                        )));
                    }
                    // Estimates and covariances must be numbers; a missing cross-covariance
                    // block or π is null.
                    let own = self.n + self.n * (self.n + 1) / 2;
                    for (k, v) in row[2..].iter().enumerate() {
                        out[(i - 1) * width + k] = match v {
                            Some(v) => *v,
                            None if k >= own => f64::NAN,
                            None => {
                                return Err(bad("a value is null (not a finite number)".into()));
                            }
                        };
                    }
                    *row_number += 1;
                }
                *next_t += 1;
                Ok(Some(t))
            }
        }
    }
}

/// Position of `P_kk` (0-based `k`) among the values `x1..xn,P1_1,P1_2..Pn_n` of a row: rows
/// `0..k` of the upper triangle hold `n, n − 1, …, n − k + 1` entries.
fn variance_index(n: usize, k: usize) -> usize {
    n + k * n - k * k.saturating_sub(1) / 2
}

/// Checks that two files describe the same chain.
pub fn same_chain(a: (&str, usize), b: (&str, usize)) -> Result<()> {
    if a.1 != b.1 {
        return Err(Error::File {
            file: a.0.to_string(),
            msg: format!(
                "holds N = {} subsystems, but {} holds N = {}: were they written for the same run?",
                a.1, b.0, b.1
            ),
        });
    }
    Ok(())
}

/// The error for two files that end at different time steps (`shorter` ends after `t`).
pub fn ends_early(shorter: &str, longer: &str, t: usize) -> Error {
    Error::File {
        file: shorter.to_string(),
        msg: format!(
            "ends after t = {t}, but {longer} goes on: were they written for the same run?"
        ),
    }
}

/// `|x̂ − x|` of subsystem `i` (0-based) at step `t`; an error when the difference of two
/// finite numbers overflows f64, which no figure can show.
pub fn drawable_error(t: usize, i: usize, estimate: f64, truth: f64) -> Result<f64> {
    let e = (estimate - truth).abs();
    if e.is_finite() {
        Ok(e)
    } else {
        Err(Error::Numerical {
            t,
            i: i + 1,
            msg: format!(
                "the error x̂ − x = {estimate:e} − ({truth:e}) overflows f64: nothing can be drawn"
            ),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::io::estimates::estimates_header;

    #[test]
    fn estimates_layout() {
        // Against the column names of the header the writer uses.
        for n in 1..=6 {
            let header = estimates_header(n);
            for k in 0..n {
                let column = format!("P{}_{}", k + 1, k + 1);
                let position = header.iter().position(|c| *c == column).unwrap() - 2;
                assert_eq!(variance_index(n, k), position, "n = {n}, k = {k}");
            }
        }
    }
}

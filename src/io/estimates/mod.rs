//! Writers of the estimates file (docs/theory.md §13): CSV `t,i,x1..xn,P1_1,P1_2..Pn_n` (the upper
//! triangle of the covariance, row by row), or JSON with the same numbers as rows of a table
//! plus the run's metadata. For the joint filter (docs/theory.md §8) the JSON rows also carry the
//! cross-covariance blocks `P_{i,i+d}`, `d = 1..k`, in columns `C{d}_{r}_{c}` (element `(r, c)`
//! of `P_{i,i+d}`, the covariance of `x(i)` and `x(i+d)`; `null` where `i + d > N`).

use std::io::Write;

use serde::{Deserialize, Serialize};

use crate::accuracy::{AccuracyReport, DetectionReport, HeldOutReport};
use crate::error::{Error, Result};
use crate::innovations::InnovationReport;
use crate::linalg::band::SymBand;
use rayon::prelude::*;

use crate::choice::{Choice, Variant};
use crate::config::ConfigSource;
use crate::filter::{Dropouts, FilterKind, InterconnectFrom, SecondMoment, Update};
use crate::interconnect::SolverKind;
use crate::io::Output;
use crate::io::csv_out::NumberFormat;
use crate::model::Model;

mod background;
pub use background::BackgroundWriter;

/// Output format of `estimate`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Format {
    Csv,
    Json,
}

impl Choice for Format {
    const VARIANTS: &'static [Variant<Self>] = &[
        Variant {
            value: Self::Csv,
            name: "csv",
            help: "",
        },
        Variant {
            value: Self::Json,
            name: "json",
            help: "",
        },
    ];
}

/// Which estimates a file holds.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum EstimateKind {
    /// `x̂(t|t)`, `P(t|t)`.
    Filtered,
    /// `x̂(t+1|t)`, `T(t+1)` on row `t`.
    Predicted,
    /// `x̂(t|T)`, `P(t|T)`.
    Smoothed,
}

/// The metadata that opens an estimates JSON file (docs/theory.md §13): written by
/// `estimate`, read back by `plot`. Fields are declared in the order they are written.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EstimatesMetadata {
    pub config: ConfigRef,
    /// The inputs file read, if any.
    pub inputs: Option<String>,
    /// The measurement file.
    pub measurements: String,
    /// State dimension.
    pub n: usize,
    pub options: EstimateOptions,
    pub sisfilt_version: String,
    /// Chain length `N`.
    pub subsystems: usize,
}

impl EstimatesMetadata {
    /// The metadata of a run on `model`, made from `config`, with the options `options` (as
    /// [`crate::run::CheckedSpec::recorded`] gives them), on the measurements and inputs named
    /// (`None`: the inputs the config generates).
    pub fn new(
        config: &ConfigSource,
        model: &Model,
        options: EstimateOptions,
        measurements: &str,
        inputs: Option<&str>,
    ) -> Self {
        Self {
            config: ConfigRef::of(config),
            inputs: inputs.map(str::to_string),
            measurements: measurements.to_string(),
            n: model.dims.n,
            options,
            sisfilt_version: env!("CARGO_PKG_VERSION").to_string(),
            subsystems: model.subsystems,
        }
    }
}

/// The config a run used: its name, the SHA-256 of its text and the values given over it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ConfigRef {
    pub path: String,
    pub sha256: String,
    /// `--set KEY=VALUE`, in order (left out when none).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub settings: Vec<String>,
}

impl ConfigRef {
    /// The name of `config` and the SHA-256 of its text, in hexadecimal.
    pub fn of(config: &ConfigSource) -> Self {
        use sha2::Digest;
        Self {
            path: config.name.clone(),
            sha256: sha2::Sha256::digest(config.text.as_bytes())
                .iter()
                .map(|b| format!("{b:02x}"))
                .collect(),
            settings: config.settings.iter().map(ToString::to_string).collect(),
        }
    }
}

/// The options of an `estimate` run.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct EstimateOptions {
    pub dropouts: Dropouts,
    pub filter: FilterKind,
    /// The two-step filter's options (`null` for the other filters, which ignore them).
    pub interconnect_from: Option<InterconnectFrom>,
    /// The joint filter's options (`--filter joint` only).
    pub joint: Option<JointSettings>,
    pub output: EstimateKind,
    /// `--paper`: the paper's two-step filter.
    pub paper: bool,
    pub second_moment: Option<SecondMoment>,
    pub solver: Option<SolverKind>,
    /// How a measurement updates the estimate (files from before the mixture update: linear).
    #[serde(default)]
    pub update: Update,
}

/// The joint filter's options as run: the band `k` (at most `N − 1`), the tolerance of
/// `A_eff`'s band, the diagonal loading and the second moment.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct JointSettings {
    pub band: usize,
    pub band_tol: f64,
    pub loading: f64,
    pub second_moment: SecondMoment,
}

/// What a run found, known only at its end: it closes an estimates JSON file (each field
/// `null` when not computed).
#[derive(Debug, Clone, Default, Serialize, Deserialize)]
pub struct EstimatesSummary {
    /// The accuracy against `--truth`.
    pub accuracy: Option<AccuracyReport>,
    /// With the mixture update and `--truth`: how well `π` detected the lost measurements.
    #[serde(default)]
    pub detection: Option<DetectionReport>,
    /// The log-likelihood of the measurements, `Σ_t` of the filter's log density of step
    /// `t` (docs/theory.md §10); `null` for Nahi's update with unknown dropouts, which has
    /// none, and for the smoothers.
    #[serde(default)]
    pub loglik: Option<f64>,
    /// Whether the measurements fit the model (docs/theory.md §14).
    #[serde(default)]
    pub innovations: Option<InnovationReport>,
    /// With readings held out of the run: how its estimates predicted them (docs/theory.md
    /// §17); absent otherwise.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub held_out: Option<HeldOutReport>,
}

/// A whole estimates JSON file: the metadata, the columns, the rows (`null` for a missing
/// cross-covariance) and the summary.
#[derive(Debug, Deserialize)]
pub struct EstimatesDocument {
    #[serde(flatten)]
    pub metadata: EstimatesMetadata,
    pub columns: Vec<String>,
    pub estimates: Vec<Vec<Option<f64>>>,
    #[serde(flatten)]
    pub summary: EstimatesSummary,
}

/// The column names of an estimates file with state dimension `n` (filtered or smoothed
/// estimates; predicted ones name their first column [`PREDICTED_STEP_COLUMN`]).
pub fn estimates_header(n: usize) -> Vec<String> {
    let mut h = vec!["t".to_string(), "i".to_string()];
    h.extend((1..=n).map(|k| format!("x{k}")));
    for r in 1..=n {
        for c in r..=n {
            h.push(format!("P{r}_{c}"));
        }
    }
    h
}

/// The JSON columns of the cross-covariance blocks `P_{i,i+d}`, `d = 1..k`, after the
/// columns of [`estimates_header`].
pub fn cross_covariance_header(n: usize, k: usize) -> Vec<String> {
    let mut h = Vec::with_capacity(k * n * n);
    for d in 1..=k {
        for r in 1..=n {
            for c in 1..=n {
                h.push(format!("C{d}_{r}_{c}"));
            }
        }
    }
    h
}

/// The first column of predicted estimates (`x̂(t+1|t)` on row `t`): the step `t` whose
/// data they are given, named so that a file says what its rows hold, and a reader cannot
/// take them for estimates of step `t` (docs/theory.md §13).
pub const PREDICTED_STEP_COLUMN: &str = "t_given";
/// The column of `π(t, i)`, the posterior probability that the measurement arrived (the
/// mixture update, docs/theory.md §10).
pub const ARRIVAL_COLUMN: &str = "arrival";
/// The column of the normalised innovation squared of `y(t, i)` (docs/theory.md §14): the
/// last of a row, when asked for.
pub const NIS_COLUMN: &str = "nis";

/// The columns of an estimates file: `t,i,x1..xn,P1_1,P1_2..Pn_n` (`t_given` for `t` when
/// the rows hold predicted estimates), then in JSON the cross-covariance blocks
/// `C{d}_{r}_{c}` of `d = 1..cross`, then `arrival` when the filter reports it, then `nis`
/// when asked for (docs/theory.md §13).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct EstimatesColumns {
    /// The rows hold `x̂(t+1|t)` and `T(t+1)` on row `t`: the first column is
    /// [`PREDICTED_STEP_COLUMN`].
    pub predicted: bool,
    /// State dimension.
    pub n: usize,
    /// Cross-covariance blocks per row.
    pub cross: usize,
    /// The column `arrival` follows the covariances.
    pub arrival: bool,
    /// The last column is `nis`.
    pub nis: bool,
}

impl EstimatesColumns {
    /// The column names, `t` and `i` included.
    pub fn header(&self) -> Vec<String> {
        let mut h = estimates_header(self.n);
        if self.predicted {
            h[0] = PREDICTED_STEP_COLUMN.to_string();
        }
        h.extend(cross_covariance_header(self.n, self.cross));
        for (name, present) in [(ARRIVAL_COLUMN, self.arrival), (NIS_COLUMN, self.nis)] {
            if present {
                h.push(name.to_string());
            }
        }
        h
    }

    /// The columns whose names are `header`, if they are those of an estimates file.
    pub fn parse(header: &[String]) -> Option<Self> {
        let mut width = header.len();
        let mut last_is = |name: &str| {
            let found = width > 0 && header[width - 1] == name;
            width -= usize::from(found);
            found
        };
        let nis = last_is(NIS_COLUMN);
        let arrival = last_is(ARRIVAL_COLUMN);
        let predicted = header.first().map(String::as_str) == Some(PREDICTED_STEP_COLUMN);
        (1..=width).find_map(|n| {
            let own = 2 + n + n * (n + 1) / 2;
            let cross = width.checked_sub(own)? / (n * n);
            let columns = Self {
                predicted,
                n,
                cross,
                arrival,
                nis,
            };
            (columns.header() == header).then_some(columns)
        })
    }

    /// Values per row after `t` and `i`.
    pub fn values(&self) -> usize {
        let n = self.n;
        n + n * (n + 1) / 2 + self.cross * n * n + usize::from(self.arrival) + usize::from(self.nis)
    }
}

/// The values of a step's rows after the covariances, one per row (`N` values each): `π`
/// for the `arrival` column and the NIS for the `nis` column; a value missing where its
/// column is written is an empty cell (CSV) or `null` (JSON).
#[derive(Debug, Clone, Copy, Default)]
pub struct RowValues<'a> {
    pub arrival: Option<&'a [f64]>,
    pub nis: Option<&'a [f64]>,
}

/// Rows formatted per batch: bounds the writer's memory whatever `N`.
const BATCH_ROWS: usize = 1 << 16;
/// Steps with at least this many rows are formatted in parallel.
const PARALLEL_MIN_ROWS: usize = 4096;
/// Rows per parallel chunk, at most.
const CHUNK_ROWS: usize = 1 << 14;

/// Streams the estimates of one time step at a time to CSV or JSON. The rows of a step are
/// formatted into reused buffers, on long chains in parallel chunks when asked
/// ([`EstimatesWriter::parallel`]; the bytes do not depend on the thread count), and written
/// in order.
pub struct EstimatesWriter<W: Write = Output> {
    out: W,
    /// The columns written (no cross-covariance blocks in CSV).
    columns: EstimatesColumns,
    format: Format,
    /// No row written yet (the first JSON row has no leading comma).
    first: bool,
    /// One buffer per chunk, sized once for the longest possible rows, and the values of
    /// its row being written.
    buffers: Vec<(Vec<u8>, Vec<f64>)>,
    /// A reader may be waiting: pass each step on as soon as it is written.
    live: bool,
    /// Format long steps in parallel chunks on the thread pool.
    parallel: bool,
}

impl<W: Write> EstimatesWriter<W> {
    /// Starts the output: the CSV header, or for JSON the metadata (when given) opening the
    /// document. CSV leaves out the cross-covariance blocks of `columns`.
    pub fn new(
        mut out: W,
        format: Format,
        mut columns: EstimatesColumns,
        metadata: Option<&EstimatesMetadata>,
    ) -> std::io::Result<Self> {
        if format == Format::Csv {
            columns.cross = 0;
        }
        let header = columns.header();
        match format {
            Format::Csv => {
                out.write_all(header.join(",").as_bytes())?;
                out.write_all(b"\n")?;
            }
            Format::Json => {
                let mut text = match metadata {
                    Some(m) => serde_json::to_string(m).map_err(std::io::Error::other)?,
                    None => "{}".into(),
                };
                text.pop(); // reopen the object
                if text.len() > 1 {
                    text.push(',');
                }
                text.push_str("\"columns\":");
                text.push_str(&serde_json::to_string(&header).expect("header serialises"));
                text.push_str(",\"estimates\":[");
                out.write_all(text.as_bytes())?;
            }
        }
        Ok(Self {
            out,
            columns,
            format,
            first: true,
            buffers: Vec::new(),
            live: false,
            parallel: false,
        })
    }

    /// The same writer, passing each step on (flushing its output) as soon as it is written
    /// when `live`: for a reader waiting at a pipe, a named pipe or a terminal.
    pub fn live(mut self, live: bool) -> Self {
        self.live = live;
        self
    }

    /// The same writer, formatting the rows of a long step in parallel chunks on the thread
    /// pool when `parallel`: for estimates written while nothing else runs (smoothed ones,
    /// after the backward pass). Beside a running filter, which has the pool, the writer
    /// formats on its own thread: the filter and the innovation check would otherwise wait
    /// for the pool's threads (8 % of the whole run on 10⁴ subsystems, docs/theory.md §13).
    pub fn parallel(mut self, parallel: bool) -> Self {
        self.parallel = parallel;
        self
    }

    /// The columns written.
    pub fn columns(&self) -> EstimatesColumns {
        self.columns
    }

    /// Writes the rows `(t, 1..N)` from `x̂` (`N·n`), `P` (`N` blocks `n × n`, column-major),
    /// the covariance band (for the cross-covariance columns; `null` without it) and the
    /// values of the `arrival` and `nis` columns.
    pub fn write_step(
        &mut self,
        t: usize,
        x: &[f64],
        p: &[f64],
        band: Option<&SymBand>,
        values: RowValues<'_>,
    ) -> std::io::Result<()> {
        let EstimatesColumns { n, cross, .. } = self.columns;
        let rows = x.len() / n;
        let arrival = self.columns.arrival.then_some(values.arrival);
        let nis = self.columns.nis.then_some(values.nis);
        let threads = rayon::current_num_threads();
        let parallel = self.parallel && rows >= PARALLEL_MIN_ROWS && threads > 1;
        let (format, first) = (self.format, self.first);
        let values = self.columns.values();
        // t, i (20 digits each), brackets and commas, each value at most 24 characters.
        let max_row = 45 + 25 * values;
        let mut start = 0;
        while start < rows {
            let batch = (rows - start).min(BATCH_ROWS);
            let chunks = if parallel {
                threads.max(batch.div_ceil(CHUNK_ROWS)).min(batch)
            } else {
                1
            };
            let per_chunk = batch.div_ceil(chunks);
            if self.buffers.len() < chunks {
                self.buffers.resize_with(chunks, Default::default);
            }
            let format_chunk = |(c, (buf, row)): (usize, &mut (Vec<u8>, Vec<f64>))| {
                buf.clear();
                buf.reserve(per_chunk * max_row);
                row.reserve(values);
                let mut fmt = NumberFormat::new();
                let from = start + c * per_chunk;
                for i in from..(from + per_chunk).min(start + batch) {
                    row.clear();
                    row.extend_from_slice(&x[i * n..(i + 1) * n]);
                    let block = &p[i * n * n..(i + 1) * n * n];
                    for r in 0..n {
                        row.extend((r..n).map(|c| block[c * n + r]));
                    }
                    // A missing value is written as an empty cell (CSV) or `null` (JSON).
                    for d in 1..=cross {
                        match band.filter(|_| i + d < rows) {
                            Some(b) => {
                                let b = b.block(i, d);
                                row.extend((0..n * n).map(|e| b[(e % n) * n + e / n]));
                            }
                            None => row.resize(row.len() + n * n, f64::NAN),
                        }
                    }
                    for column in [arrival, nis].into_iter().flatten() {
                        row.push(column.map_or(f64::NAN, |a| a[i]));
                    }
                    let row = row.iter().copied();
                    match format {
                        Format::Csv => fmt.csv_row(buf, t, i + 1, row),
                        Format::Json => fmt.json_row(buf, first && i == 0, t, i + 1, row),
                    }
                }
            };
            if parallel {
                self.buffers[..chunks]
                    .par_iter_mut()
                    .enumerate()
                    .for_each(format_chunk);
            } else {
                self.buffers[..chunks]
                    .iter_mut()
                    .enumerate()
                    .for_each(format_chunk);
            }
            for (buf, _) in &self.buffers[..chunks] {
                self.out.write_all(buf)?;
            }
            start += batch;
        }
        self.first &= rows == 0;
        if self.live {
            self.out.flush()?;
        }
        Ok(())
    }

    /// Closes the document (JSON gets the fields of `summary`), flushes and returns the
    /// writer.
    pub fn finish(mut self, summary: &EstimatesSummary) -> std::io::Result<W> {
        if self.format == Format::Json {
            let fields = serde_json::to_string(summary).expect("the summary serialises");
            writeln!(self.out, "],{}", &fields[1..])?;
        }
        self.out.flush()?;
        Ok(self.out)
    }
}

impl EstimatesWriter<Output> {
    /// [`EstimatesWriter::finish`], then commits the output (renames a file into place).
    pub fn commit(self, summary: &EstimatesSummary) -> Result<()> {
        let name = self.out.name();
        let out = self.finish(summary).map_err(|e| Error::io(name, e))?;
        out.commit()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn columns(n: usize) -> EstimatesColumns {
        EstimatesColumns {
            predicted: false,
            n,
            cross: 0,
            arrival: false,
            nis: false,
        }
    }

    /// The writer thread, batching steps of short chains, writes the same bytes as the writer
    /// called directly, the `arrival` and `nis` columns included.
    #[test]
    fn background_writer_equals_direct_writer() {
        for (n, rows, steps) in [(2, 3, 2000), (1, 5000, 3), (3, 700, 20)] {
            let x: Vec<f64> = (0..rows * n).map(|k| (k as f64 * 0.3).cos()).collect();
            let p: Vec<f64> = (0..rows * n * n).map(|k| k as f64 / 9.0).collect();
            let pi: Vec<f64> = (0..rows).map(|k| 1.0 / (1.0 + k as f64)).collect();
            let nis_values: Vec<f64> = (0..rows).map(|k| 2.0 + k as f64).collect();
            for (arrival, nis) in [(false, false), (true, false), (false, true), (true, true)] {
                let columns = EstimatesColumns {
                    arrival,
                    nis,
                    ..columns(n)
                };
                let new = || EstimatesWriter::new(Vec::new(), Format::Csv, columns, None).unwrap();
                let mut direct = new();
                let mut background = BackgroundWriter::new(new(), rows);
                for t in 1..=steps {
                    // Every third step comes without π: an empty cell.
                    let values = RowValues {
                        arrival: (t % 3 != 0).then_some(pi.as_slice()),
                        nis: Some(&nis_values),
                    };
                    direct.write_step(t, &x, &p, None, values).unwrap();
                    background.write_step(t, &x, &p, None, values).unwrap();
                }
                let (writer, _) = background.finish().unwrap();
                let summary = EstimatesSummary::default();
                let bytes = writer.finish(&summary).unwrap();
                assert!(bytes == direct.finish(&summary).unwrap());
                let text = String::from_utf8(bytes).unwrap();
                let header = text.lines().next().unwrap();
                assert_eq!(header.ends_with(",arrival"), arrival && !nis);
                assert_eq!(header.ends_with(",nis"), nis);
                let row = |k: usize| text.lines().nth(k).unwrap();
                match (arrival, nis) {
                    // Row (t = 1, i = 2) ends in π = 1/2; row (t = 3, i = 1) in an empty cell.
                    (true, false) => {
                        assert!(row(2).ends_with(",0.5"));
                        assert!(row(2 * rows + 1).ends_with(','));
                    }
                    // …and then the NIS, 3 for i = 2 and 2 for i = 1.
                    (true, true) => {
                        assert!(row(2).ends_with(",0.5,3.0"));
                        assert!(row(2 * rows + 1).ends_with(",,2.0"));
                    }
                    (false, true) => assert!(row(2).ends_with(",3.0")),
                    (false, false) => {}
                }
            }
        }
    }

    /// The columns read back from their names are the columns written.
    #[test]
    fn columns_parse_their_header() {
        for (n, predicted) in (1..=4).flat_map(|n| [(n, false), (n, true)]) {
            for cross in 0..=3 {
                for (arrival, nis) in [(false, false), (true, false), (false, true), (true, true)] {
                    let columns = EstimatesColumns {
                        predicted,
                        n,
                        cross,
                        arrival,
                        nis,
                    };
                    let header = columns.header();
                    assert_eq!(EstimatesColumns::parse(&header), Some(columns));
                    assert_eq!(header.len(), 2 + columns.values());
                    let mut renamed = header.clone();
                    renamed[2] = "y1".into();
                    assert_eq!(EstimatesColumns::parse(&renamed), None);
                    let mut renamed = header.clone();
                    renamed[0] = "time".into();
                    assert_eq!(EstimatesColumns::parse(&renamed), None);
                    // Without its last column, a header is another one only when that
                    // column was `nis` or `arrival`, or a whole 1 × 1 cross-covariance block.
                    let without_last = EstimatesColumns::parse(&header[..header.len() - 1]);
                    let expected = match (nis, arrival, n, cross) {
                        (true, _, _, _) => Some(EstimatesColumns {
                            nis: false,
                            ..columns
                        }),
                        (false, true, _, _) => Some(EstimatesColumns {
                            arrival: false,
                            ..columns
                        }),
                        (false, false, 1, 1..) => Some(EstimatesColumns {
                            cross: cross - 1,
                            ..columns
                        }),
                        _ => None,
                    };
                    assert_eq!(without_last, expected);
                }
            }
        }
    }

    /// Rows written by the parallel chunked path equal rows formatted one by one.
    #[test]
    fn chunked_rows_equal_single_rows() {
        let (n, rows) = (2, 5000);
        let x: Vec<f64> = (0..rows * n)
            .map(|k| (k as f64 * 0.37).sin() * 1e3)
            .collect();
        let p: Vec<f64> = (0..rows * n * n).map(|k| (k as f64).cos() / 7.0).collect();
        for format in [Format::Csv, Format::Json] {
            let mut expected = Vec::new();
            let mut fmt = NumberFormat::new();
            for t in 1..=2 {
                for i in 0..rows {
                    let b = &p[i * 4..i * 4 + 4];
                    let row = [x[2 * i], x[2 * i + 1], b[0], b[2], b[3]].into_iter();
                    match format {
                        Format::Csv => fmt.csv_row(&mut expected, t, i + 1, row),
                        Format::Json => {
                            fmt.json_row(&mut expected, t == 1 && i == 0, t, i + 1, row)
                        }
                    }
                }
            }
            for threads in [1, 2, 3] {
                let pool = rayon::ThreadPoolBuilder::new()
                    .num_threads(threads)
                    .build()
                    .unwrap();
                let bytes = pool.install(|| {
                    let mut w = EstimatesWriter::new(Vec::new(), format, columns(n), None)
                        .unwrap()
                        .parallel(true);
                    w.write_step(1, &x, &p, None, RowValues::default()).unwrap();
                    w.write_step(2, &x, &p, None, RowValues::default()).unwrap();
                    w.finish(&EstimatesSummary::default()).unwrap()
                });
                let header = match format {
                    Format::Csv => "t,i,x1,x2,P1_1,P1_2,P2_2\n".to_string(),
                    Format::Json => {
                        "{\"columns\":[\"t\",\"i\",\"x1\",\"x2\",\"P1_1\",\"P1_2\",\"P2_2\"],\"estimates\":[".to_string()
                    }
                };
                let mut want = header.into_bytes();
                want.extend_from_slice(&expected);
                if format == Format::Json {
                    want.extend_from_slice(
                        b"],\"accuracy\":null,\"detection\":null,\"loglik\":null,\"innovations\":null}\n",
                    );
                }
                assert!(bytes == want, "{format:?} with {threads} threads");
            }
        }
    }
}

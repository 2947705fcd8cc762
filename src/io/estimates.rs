//! Writers of the estimates file (SPEC §6): CSV `t,i,x1..xn,P1_1,P1_2..Pn_n` (the upper
//! triangle of the covariance, row by row), or JSON with the same numbers as rows of a table
//! plus the run's metadata. For the joint filter (SPEC §9) the JSON rows also carry the
//! cross-covariance blocks `P_{i,i+d}`, `d = 1..k`, in columns `C{d}_{r}_{c}` (element `(r, c)`
//! of `P_{i,i+d}`, the covariance of `x(i)` and `x(i+d)`; `null` where `i + d > N`).

use std::io::Write;

use serde::Serialize;

use crate::accuracy::AccuracyReport;
use crate::error::{Error, Result};
use crate::io::{CsvWriter, Output};

/// Output format of `estimate`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Format {
    Csv,
    Json,
}

/// The column names of an estimates file with state dimension `n`.
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

/// Streams estimate rows to CSV or JSON.
pub struct EstimatesWriter {
    n: usize,
    /// Cross-covariance blocks per JSON row (`k`; 0 for none).
    cross: usize,
    row: Vec<f64>,
    kind: Kind,
}

enum Kind {
    Csv(CsvWriter<Output>),
    Json {
        out: Output,
        first: bool,
        ryu: ryu::Buffer,
    },
}

impl EstimatesWriter {
    /// Starts the output; for JSON, `metadata` (an object) opens the document and each row
    /// carries `cross` cross-covariance blocks (see [`cross_covariance_header`]).
    pub fn new(
        out: Output,
        format: Format,
        n: usize,
        cross: usize,
        metadata: serde_json::Value,
    ) -> Result<Self> {
        let mut header = estimates_header(n);
        let name = out.name();
        let kind = match format {
            Format::Csv => {
                Kind::Csv(CsvWriter::new(out, &header).map_err(|e| Error::io(&name, e))?)
            }
            Format::Json => {
                header.extend(cross_covariance_header(n, cross));
                let mut out = out;
                let mut text = serde_json::to_string(&metadata).expect("metadata serialises");
                text.pop(); // reopen the object
                if text.len() > 1 {
                    text.push(',');
                }
                text.push_str("\"columns\":");
                text.push_str(&serde_json::to_string(&header).expect("header serialises"));
                text.push_str(",\"estimates\":[");
                out.write_all(text.as_bytes())
                    .map_err(|e| Error::io(&name, e))?;
                Kind::Json {
                    out,
                    first: true,
                    ryu: ryu::Buffer::new(),
                }
            }
        };
        Ok(Self {
            n,
            cross: if format == Format::Json { cross } else { 0 },
            row: Vec::with_capacity(n + n * (n + 1) / 2 + cross * n * n),
            kind,
        })
    }

    /// Writes the row of `(t, i)` from `x̂` (`n`) and `P` (`n × n`, column-major); `cross`
    /// gives the block `P_{i,i+d}` (column-major) for `d = 1..k`, or `None` past the chain's end.
    pub fn row<'a>(
        &mut self,
        t: usize,
        i: usize,
        x: &[f64],
        p: &[f64],
        cross: impl Fn(usize) -> Option<&'a [f64]>,
    ) -> std::io::Result<()> {
        let n = self.n;
        self.row.clear();
        self.row.extend_from_slice(x);
        for r in 0..n {
            for c in r..n {
                self.row.push(p[c * n + r]);
            }
        }
        for d in 1..=self.cross {
            match cross(d) {
                Some(b) => {
                    for r in 0..n {
                        for c in 0..n {
                            self.row.push(b[c * n + r]);
                        }
                    }
                }
                None => self.row.extend(std::iter::repeat_n(f64::NAN, n * n)),
            }
        }
        match &mut self.kind {
            Kind::Csv(w) => w.row(t, i, &self.row, None),
            Kind::Json { out, first, ryu } => {
                if !*first {
                    out.write_all(b",")?;
                }
                *first = false;
                write!(out, "[{t},{i}")?;
                for v in &self.row {
                    out.write_all(b",")?;
                    if v.is_finite() {
                        out.write_all(ryu.format_finite(*v).as_bytes())?;
                    } else {
                        out.write_all(b"null")?;
                    }
                }
                out.write_all(b"]")
            }
        }
    }

    /// Closes the document (JSON gets `accuracy`, or `null`) and commits the output.
    pub fn finish(self, accuracy: Option<&AccuracyReport>) -> Result<()> {
        match self.kind {
            Kind::Csv(w) => {
                let out = w.into_inner().map_err(|e| Error::io("<output>", e))?;
                out.commit()
            }
            Kind::Json { mut out, .. } => {
                let name = out.name();
                let acc = serde_json::to_string(&accuracy).expect("accuracy serialises");
                writeln!(out, "],\"accuracy\":{acc}}}").map_err(|e| Error::io(&name, e))?;
                out.commit()
            }
        }
    }
}

//! The checks of config values, each naming the TOML key it refused (docs/theory.md §13):
//! finite numbers, counts, shapes, symmetric, semidefinite and definite matrices,
//! probabilities and ranges.

use nalgebra::{DMatrix, SymmetricEigen};

use crate::config::{ConfigSetting, RawMatrix};
use crate::error::{Error, Result};

/// Relative tolerance of the symmetry and semidefiniteness checks on config matrices.
const SYMMETRY_TOL: f64 = 1e-10;

/// Checks the values of the config `file`; each error names the file and the key, and says
/// when the value came from a `--set` (one of `settings`).
pub(super) struct Checker<'a> {
    pub(super) file: &'a str,
    pub(super) settings: &'a [ConfigSetting],
}

impl Checker<'_> {
    pub(super) fn err(&self, key: &str, msg: impl Into<String>) -> Error {
        let set = self.settings.iter().any(|s| s.covers(key));
        Error::Config {
            file: self.file.to_string(),
            key: if set {
                format!("{key} (from --set)")
            } else {
                key.to_string()
            },
            msg: msg.into(),
        }
    }

    pub(super) fn finite(&self, key: &str, x: f64) -> Result<f64> {
        if x.is_finite() {
            Ok(x)
        } else {
            Err(self.err(key, format!("expected a finite number, found {x}")))
        }
    }

    pub(super) fn count(&self, key: &str, x: i64, min: i64) -> Result<usize> {
        if x < min {
            Err(self.err(key, format!("expected an integer ≥ {min}, found {x}")))
        } else {
            Ok(x as usize)
        }
    }

    /// Shape of a raw matrix; rejects ragged rows and non-finite entries.
    pub(super) fn shape(&self, key: &str, raw: &RawMatrix) -> Result<(usize, usize)> {
        let cols = raw.first().map_or(0, Vec::len);
        for (r, row) in raw.iter().enumerate() {
            if row.len() != cols {
                return Err(self.err(
                    key,
                    format!(
                        "ragged matrix: row 1 has {cols} entries but row {} has {}",
                        r + 1,
                        row.len()
                    ),
                ));
            }
            for &x in row {
                self.finite(key, x)?;
            }
        }
        Ok((raw.len(), cols))
    }

    /// Converts a raw matrix, checking it is `rows × cols`; `what` names the expected shape.
    pub(super) fn matrix(
        &self,
        key: &str,
        raw: &RawMatrix,
        rows: usize,
        cols: usize,
        what: &str,
    ) -> Result<DMatrix<f64>> {
        let (r, c) = self.shape(key, raw)?;
        // An empty list stands for any matrix with a zero dimension.
        let ok = (r, c) == (rows, cols) || (r == 0 && (rows == 0 || cols == 0));
        if !ok {
            return Err(self.err(
                key,
                format!("expected {rows} × {cols} ({what}), found {r} × {c}"),
            ));
        }
        Ok(DMatrix::from_fn(rows, cols, |i, j| raw[i][j]))
    }

    pub(super) fn symmetric(&self, key: &str, a: &DMatrix<f64>) -> Result<()> {
        let scale = a.amax().max(f64::MIN_POSITIVE);
        for i in 0..a.nrows() {
            for j in 0..i {
                if (a[(i, j)] - a[(j, i)]).abs() > SYMMETRY_TOL * scale {
                    return Err(self.err(
                        key,
                        format!(
                            "expected a symmetric matrix, but entry ({}, {}) = {} differs from ({}, {}) = {}",
                            i + 1,
                            j + 1,
                            a[(i, j)],
                            j + 1,
                            i + 1,
                            a[(j, i)]
                        ),
                    ));
                }
            }
        }
        Ok(())
    }

    pub(super) fn positive_semidefinite(&self, key: &str, a: &DMatrix<f64>) -> Result<()> {
        self.symmetric(key, a)?;
        if a.is_empty() {
            return Ok(());
        }
        let eig = SymmetricEigen::new(a.clone());
        let min = eig.eigenvalues.min();
        let scale = eig.eigenvalues.amax();
        if min < -SYMMETRY_TOL * scale {
            return Err(self.err(
                key,
                format!(
                    "expected a positive semidefinite matrix, but it has the eigenvalue {min:e}"
                ),
            ));
        }
        Ok(())
    }

    pub(super) fn positive_definite(&self, key: &str, a: &DMatrix<f64>) -> Result<()> {
        self.symmetric(key, a)?;
        if a.nrows() > 0 && a.clone().cholesky().is_none() {
            let min = SymmetricEigen::new(a.clone()).eigenvalues.min();
            return Err(self.err(
                key,
                format!("expected a positive definite matrix, but it has the eigenvalue {min:e}"),
            ));
        }
        Ok(())
    }

    pub(super) fn probability(&self, key: &str, p: f64) -> Result<f64> {
        self.finite(key, p)?;
        if !(0.0..=1.0).contains(&p) {
            return Err(self.err(key, format!("expected a probability in [0, 1], found {p}")));
        }
        Ok(p)
    }

    /// An inclusive range `[first, last]` with `1 ≤ first ≤ last` (and `last ≤ max` if given).
    pub(super) fn range(
        &self,
        key: &str,
        r: [i64; 2],
        max: Option<usize>,
    ) -> Result<(usize, usize)> {
        let [first, last] = r;
        let bounds = match max {
            Some(max) => format!("within 1..{max}"),
            None => "starting at 1 or later".to_string(),
        };
        if first < 1 || max.is_some_and(|m| last as u64 > m as u64) {
            return Err(self.err(
                key,
                format!("expected a range [first, last] {bounds}, found [{first}, {last}]"),
            ));
        }
        if last < first {
            return Err(self.err(
                key,
                format!("expected first ≤ last, found the reversed range [{first}, {last}]"),
            ));
        }
        Ok((first as usize, last as usize))
    }
}

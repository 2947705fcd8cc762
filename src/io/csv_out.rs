//! CSV writer for the per-`(t, i)` files of docs/theory.md §13. Numbers are written in the shortest form
//! that reads back to the same bits, integers with `itoa`; one reused line buffer, so writing
//! allocates nothing per row.

use std::io::Write;

/// Number formatting of the CSV and JSON rows: floats in the shortest form that reads back to
/// the same bits (`zmij`, with the exponent written as `1e16`, `1e-7`), integers with `itoa`,
/// appended to a byte buffer.
#[derive(Default)]
pub struct NumberFormat {
    float: zmij::Buffer,
    int: itoa::Buffer,
}

impl NumberFormat {
    pub fn new() -> Self {
        Self::default()
    }

    /// Appends `v` (finite or infinite, not NaN).
    #[inline]
    fn push_float(&mut self, line: &mut Vec<u8>, v: f64) {
        let text = self.float.format(v).as_bytes();
        // zmij writes a positive exponent as `e+16`; our files have always had `e16` (the
        // form of `ryu` and of Rust's `{:e}`), and their bytes must not change. A positive
        // exponent is written exactly from 1e16 on (it is a double, so nothing below it
        // prints as 1e16 or more).
        if v.abs() < 1e16 {
            line.extend_from_slice(text);
        } else if let Some(plus) = text.iter().position(|&b| b == b'+') {
            line.extend_from_slice(&text[..plus]);
            line.extend_from_slice(&text[plus + 1..]);
        } else {
            line.extend_from_slice(text);
        }
    }

    /// Appends the line `t,i,v1,…\n`; a NaN value is an empty cell (a lost measurement).
    #[inline]
    pub fn csv_row(
        &mut self,
        line: &mut Vec<u8>,
        t: usize,
        i: usize,
        values: impl Iterator<Item = f64>,
    ) {
        self.push_int(line, t);
        line.push(b',');
        self.push_int(line, i);
        for v in values {
            line.push(b',');
            if !v.is_nan() {
                self.push_float(line, v);
            }
        }
        line.push(b'\n');
    }

    /// Appends the integer `k`.
    #[inline]
    pub fn push_int(&mut self, line: &mut Vec<u8>, k: impl itoa::Integer) {
        line.extend_from_slice(self.int.format(k).as_bytes());
    }

    /// Appends the JSON array `[t,i,v1,…]`, preceded by a comma unless `first`; a value that
    /// is not finite is `null`.
    #[inline]
    pub fn json_row(
        &mut self,
        line: &mut Vec<u8>,
        first: bool,
        t: usize,
        i: usize,
        values: impl Iterator<Item = f64>,
    ) {
        if !first {
            line.push(b',');
        }
        line.push(b'[');
        self.push_int(line, t);
        line.push(b',');
        self.push_int(line, i);
        for v in values {
            line.push(b',');
            if v.is_finite() {
                self.push_float(line, v);
            } else {
                line.extend_from_slice(b"null");
            }
        }
        line.push(b']');
    }
}

/// Writes `t,i,values…` rows.
pub struct CsvWriter<W: Write> {
    out: W,
    line: Vec<u8>,
    format: NumberFormat,
}

impl<W: Write> CsvWriter<W> {
    /// Wraps a writer (which should be buffered) and writes the header line.
    pub fn new(mut out: W, header: &[String]) -> std::io::Result<Self> {
        out.write_all(header.join(",").as_bytes())?;
        out.write_all(b"\n")?;
        Ok(Self {
            out,
            line: Vec::with_capacity(256),
            format: NumberFormat::new(),
        })
    }

    /// Writes one row: `t`, `i`, each value (NaN as an empty cell: a lost measurement), and
    /// optionally a trailing integer (the truth file's `gamma`).
    pub fn row(
        &mut self,
        t: usize,
        i: usize,
        values: &[f64],
        tail: Option<u8>,
    ) -> std::io::Result<()> {
        self.line.clear();
        self.format
            .csv_row(&mut self.line, t, i, values.iter().copied());
        if let Some(k) = tail {
            self.line.pop();
            self.line.push(b',');
            self.format.push_int(&mut self.line, k);
            self.line.push(b'\n');
        }
        self.out.write_all(&self.line)
    }

    /// Flushes and returns the inner writer.
    pub fn into_inner(mut self) -> std::io::Result<W> {
        self.out.flush()?;
        Ok(self.out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn numbers_round_trip_and_missing_is_empty() {
        let mut w = CsvWriter::new(
            Vec::new(),
            &["t".into(), "i".into(), "y1".into(), "y2".into()],
        )
        .unwrap();
        let v = 0.1 + 0.2;
        w.row(3, 12, &[v, f64::NAN], Some(1)).unwrap();
        let text = String::from_utf8(w.into_inner().unwrap()).unwrap();
        let line = text.lines().nth(1).unwrap();
        assert_eq!(line, "3,12,0.30000000000000004,,1");
        let back: f64 = line.split(',').nth(2).unwrap().parse().unwrap();
        assert_eq!(back.to_bits(), v.to_bits());
    }

    /// The bytes of every float are those `ryu` wrote before (an independent implementation
    /// of the same shortest form) and read back to the same bits: edge cases, random bit
    /// patterns, and random decimals across the switch to exponents (below 1e-5, from 1e16).
    #[test]
    fn floats_are_written_as_ryu_writes_them() {
        use rand::{RngExt, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        let edges = [
            0.0,
            -0.0,
            1.0,
            -1.0,
            0.1,
            1e-5,
            9.999e-6,
            1e-6,
            1e15,
            9.999e15,
            1e16,
            1e22,
            1e100,
            5e-324,
            f64::MIN_POSITIVE,
            f64::MAX,
            f64::MIN,
            f64::INFINITY,
            f64::NEG_INFINITY,
        ];
        let random_bits: Vec<f64> = (0..300_000)
            .map(|_| f64::from_bits(rng.random::<u64>()))
            .collect();
        let decimals: Vec<f64> = (0..300_000)
            .map(|_| (rng.random::<f64>() - 0.5) * 10f64.powi(rng.random_range(-9..20)))
            .collect();
        let (mut fmt, mut reference) = (NumberFormat::new(), ryu::Buffer::new());
        let mut line = Vec::new();
        let mut exponents = 0;
        for v in edges.into_iter().chain(random_bits).chain(decimals) {
            if v.is_nan() {
                continue;
            }
            line.clear();
            fmt.push_float(&mut line, v);
            let text = std::str::from_utf8(&line).unwrap();
            assert_eq!(text, reference.format(v), "{v:e}");
            exponents += usize::from(text.contains('e'));
            let back: f64 = text.parse().unwrap();
            assert_eq!(back.to_bits(), v.to_bits(), "{text}");
        }
        assert!(exponents > 100_000, "both notations are exercised");
    }
}

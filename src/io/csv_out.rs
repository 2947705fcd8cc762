//! CSV writer for the per-`(t, i)` files of docs/theory.md §13. Numbers are written in the shortest form
//! that reads back to the same bits (`ryu`), integers with `itoa`; one reused line buffer, so
//! writing allocates nothing per row.

use std::io::Write;

/// Number formatting of the CSV and JSON rows: shortest round-trip floats (`ryu`), integers
/// with `itoa`, appended to a byte buffer.
pub struct NumberFormat<'a> {
    pub ryu: &'a mut ryu::Buffer,
    pub itoa: &'a mut itoa::Buffer,
}

impl NumberFormat<'_> {
    /// Appends the line `t,i,v1,…\n`; a NaN value is an empty cell (a lost measurement).
    #[inline]
    pub fn csv_row(
        &mut self,
        line: &mut Vec<u8>,
        t: usize,
        i: usize,
        values: impl Iterator<Item = f64>,
    ) {
        line.extend_from_slice(self.itoa.format(t).as_bytes());
        line.push(b',');
        line.extend_from_slice(self.itoa.format(i).as_bytes());
        for v in values {
            line.push(b',');
            if !v.is_nan() {
                line.extend_from_slice(self.ryu.format(v).as_bytes());
            }
        }
        line.push(b'\n');
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
        line.extend_from_slice(self.itoa.format(t).as_bytes());
        line.push(b',');
        line.extend_from_slice(self.itoa.format(i).as_bytes());
        for v in values {
            line.push(b',');
            if v.is_finite() {
                line.extend_from_slice(self.ryu.format_finite(v).as_bytes());
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
    ryu: ryu::Buffer,
    itoa: itoa::Buffer,
}

impl<W: Write> CsvWriter<W> {
    /// Wraps a writer (which should be buffered) and writes the header line.
    pub fn new(mut out: W, header: &[String]) -> std::io::Result<Self> {
        out.write_all(header.join(",").as_bytes())?;
        out.write_all(b"\n")?;
        Ok(Self {
            out,
            line: Vec::with_capacity(256),
            ryu: ryu::Buffer::new(),
            itoa: itoa::Buffer::new(),
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
        let mut fmt = NumberFormat {
            ryu: &mut self.ryu,
            itoa: &mut self.itoa,
        };
        fmt.csv_row(&mut self.line, t, i, values.iter().copied());
        if let Some(k) = tail {
            self.line.pop();
            self.line.push(b',');
            self.line.extend_from_slice(self.itoa.format(k).as_bytes());
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
}

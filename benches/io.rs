//! The reading and writing of `estimate` without the filter (`cargo bench --bench io`), on
//! rows of workload W (n = 2, q = 1: a measurement row `t,i,y1`, an estimates row
//! `t,i,x1,x2,P1_1,P1_2,P2_2`), 10⁴ rows a step, one thread, and the floors under them
//! (issue 42). Group `io`, every throughput in rows:
//! - `write`: the estimates writer formatting a step's rows (CSV) into a sink;
//! - `write_floor`: the five floats of each row formatted by `zmij` alone, nothing copied;
//! - `read`: the measurement reader parsing and checking a step's rows from memory;
//! - `read_split`: the `csv` crate splitting the same rows into fields, nothing parsed;
//! - `read_floor`: `str::parse::<f64>` of each row's value alone.
//!
//! `write_floor + read_floor + read_split` per row is what the command line cannot do
//! without while it writes the shortest round-trip text of every number and reads CSV
//! through the `csv` crate; BENCHMARKS.md sets it against issue 42's target.

use std::hint::black_box;

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use sisfilt::io::estimates::{EstimatesColumns, EstimatesWriter, Format, RowValues};
use sisfilt::io::{StepLayout, StepReader};

const ROWS: usize = 10_000;
const STEPS: usize = 10;

/// Values of the size and spread of W's estimates: `x̂` of order 1, `P` of order 0.03.
fn step_values() -> (Vec<f64>, Vec<f64>) {
    let x = (0..2 * ROWS)
        .map(|k| (k as f64 * 0.37).sin() * 1.7)
        .collect();
    let p = (0..4 * ROWS)
        .map(|k| 0.03 + 1e-3 * (k as f64 * 0.11).cos())
        .collect();
    (x, p)
}

/// A measurement file of `STEPS` steps of `ROWS` rows, as `simulate` writes it.
fn measurement_file() -> Vec<u8> {
    let mut text = b"t,i,y1\n".to_vec();
    for t in 1..=STEPS {
        for i in 1..=ROWS {
            let y = ((t * ROWS + i) as f64 * 0.29).sin() * 0.8;
            text.extend_from_slice(format!("{t},{i},{y:?}\n").as_bytes());
        }
    }
    text
}

fn io(c: &mut Criterion) {
    let mut group = c.benchmark_group("io");
    group.sample_size(20);
    let (x, p) = step_values();
    let columns = EstimatesColumns {
        predicted: false,
        n: 2,
        cross: 0,
        arrival: false,
        nis: false,
    };

    group.throughput(Throughput::Elements(ROWS as u64));
    let mut writer = EstimatesWriter::new(std::io::sink(), Format::Csv, columns, None).unwrap();
    group.bench_function("write", |b| {
        b.iter(|| {
            writer
                .write_step(1, &x, &p, None, RowValues::default())
                .unwrap()
        })
    });
    group.bench_function("write_floor", |b| {
        let mut buffer = zmij::Buffer::new();
        b.iter(|| {
            let mut bytes = 0;
            for i in 0..ROWS {
                let block = &p[4 * i..4 * i + 4];
                for v in [x[2 * i], x[2 * i + 1], block[0], block[2], block[3]] {
                    bytes += buffer.format_finite(black_box(v)).len();
                }
            }
            bytes
        })
    });

    let file = measurement_file();
    group.throughput(Throughput::Elements((STEPS * ROWS) as u64));
    group.bench_function("read", |b| {
        let mut y = vec![0.0; ROWS];
        b.iter(|| {
            let layout = StepLayout::measurements(1);
            let mut reader = StepReader::new("bench", file.as_slice(), layout, ROWS).unwrap();
            while reader.read_step(&mut y).unwrap().is_some() {}
            y[ROWS - 1]
        })
    });
    group.bench_function("read_split", |b| {
        let mut record = csv::ByteRecord::new();
        b.iter(|| {
            let mut reader = csv::ReaderBuilder::new()
                .has_headers(false)
                .flexible(true)
                .buffer_capacity(1 << 16)
                .from_reader(file.as_slice());
            let mut fields = 0;
            while reader.read_byte_record(&mut record).unwrap() {
                fields += record.len();
            }
            fields
        })
    });
    let values: Vec<&str> = std::str::from_utf8(&file)
        .unwrap()
        .lines()
        .skip(1)
        .map(|line| line.rsplit(',').next().unwrap())
        .collect();
    group.bench_function("read_floor", |b| {
        b.iter(|| {
            values
                .iter()
                .map(|v| black_box(v).parse::<f64>().unwrap())
                .sum::<f64>()
        })
    });
    group.finish();
}

criterion_group!(benches, io);
criterion_main!(benches);

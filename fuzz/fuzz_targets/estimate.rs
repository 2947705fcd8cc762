//! The whole `estimate` path in memory on a fuzzed config and measurement file: the config is
//! read and checked, a run spec is chosen by four control bytes (every filter, update, dropout
//! mode and output: filtered, predicted or smoothed, the joint filter's band), the measurements
//! stream through the filter or smoother, and the estimates are written as CSV or JSON. It
//! must never panic, never write a number that is not finite (a breakdown is an error naming
//! `t` and `i`), and every error must be one line.
//!
//! Input: four control bytes, the config's text, a zero byte, the measurement CSV.
#![no_main]

#[path = "small_model.rs"]
mod small_model;

use libfuzzer_sys::fuzz_target;
use sisfilt::filter::{Dropouts, FilterKind, Update};
use sisfilt::inputs::InputStream;
use sisfilt::io::estimates::{EstimatesSummary, EstimatesWriter, Format, RowValues};
use sisfilt::io::{StepLayout, StepReader};
use sisfilt::run::{EstimateSink, FileSource, Note, RunSpec, StepEstimates};
use small_model::{check_message, small_model};

/// Writes every step as `estimate --out` does, and checks it is finite first.
struct Sink {
    writer: EstimatesWriter<Vec<u8>>,
}

impl EstimateSink for Sink {
    fn step(&mut self, step: &StepEstimates<'_>) -> sisfilt::Result<()> {
        assert!(
            step.x.iter().chain(step.p).all(|v| v.is_finite()),
            "t = {}: not finite",
            step.t
        );
        let values = RowValues {
            arrival: step.arrival,
            nis: Some(step.nis),
        };
        self.writer
            .write_step(step.t, step.x, step.p, step.band, values)
            .expect("writing to memory");
        Ok(())
    }

    fn note(&mut self, note: Note) {
        assert!(!note.to_string().contains('\n'), "multi-line note: {note}");
    }
}

fuzz_target!(|data: &[u8]| {
    let Some((controls, rest)) = data.split_first_chunk::<4>() else {
        return;
    };
    let Some(split) = rest.iter().position(|&b| b == 0) else {
        return;
    };
    let (config, meas) = (&rest[..split], &rest[split + 1..]);
    let Some(model) = small_model(config) else {
        return;
    };
    let [filter, modes, band, format] = *controls;
    let filter = [
        FilterKind::Distributed,
        FilterKind::Centralized,
        FilterKind::Joint,
    ][filter as usize % 3];
    let spec = RunSpec {
        filter,
        update: if modes & 1 == 1 {
            Update::Mixture
        } else {
            Update::Linear
        },
        dropouts: if modes & 2 == 2 {
            Dropouts::Known
        } else {
            Dropouts::Unknown
        },
        paper: modes & 4 == 4 && filter == FilterKind::Distributed,
        smooth: modes & 8 == 8,
        predicted: modes & 16 == 16 && modes & 8 == 0,
        band: (filter == FilterKind::Joint).then_some(band as usize % 6),
        nis_column: modes & 32 == 32,
        ..RunSpec::default()
    };
    let spec = match spec.check() {
        Ok(spec) => spec,
        Err(_) => return,
    };
    let layout = StepLayout {
        allow_empty: spec.dropouts() == Dropouts::Known,
        ..StepLayout::measurements(model.dims.q)
    };
    let reader = match StepReader::new("fuzz.csv", meas, layout, model.subsystems) {
        Ok(reader) => reader,
        Err(e) => return check_message(&e),
    };
    let inputs = match InputStream::open(&model, None) {
        Ok(inputs) => inputs,
        Err(e) => return check_message(&e),
    };
    let mut source = FileSource::new(reader, inputs);
    let format = if format & 1 == 1 {
        Format::Json
    } else {
        Format::Csv
    };
    let writer = EstimatesWriter::new(Vec::new(), format, spec.columns(&model), None)
        .expect("writing to memory");
    let mut sink = Sink { writer };
    match sisfilt::run::stream(&model, &spec, &mut source, None, &mut sink) {
        Ok(report) => {
            let bytes = sink
                .writer
                .finish(&report.summary)
                .expect("writing to memory");
            if format == Format::Json {
                let _: serde_json::Value =
                    serde_json::from_slice(&bytes).expect("the estimates are JSON");
            }
        }
        Err(e) => {
            check_message(&e);
            let _ = sink.writer.finish(&EstimatesSummary::default());
        }
    }
});

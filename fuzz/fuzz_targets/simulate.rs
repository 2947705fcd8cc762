//! `simulate` in memory on a fuzzed config: the chain is read and checked, simulated for at
//! most 64 steps with the seed of the first eight bytes, and every step's truth and
//! measurements are written as `simulate` writes them. It must never panic, never hand out a
//! number that is not finite (an unstable chain is an error naming `t` and `i`), and every
//! error must be one line.
//!
//! Input: eight bytes of seed, then the config's text.
#![no_main]

#[path = "small_model.rs"]
mod small_model;

use libfuzzer_sys::fuzz_target;
use sisfilt::inputs::InputStream;
use sisfilt::io::{CsvWriter, StepLayout};
use small_model::{check_message, small_model};

/// At most this many steps.
const MAX_STEPS: usize = 64;

fuzz_target!(|data: &[u8]| {
    let Some((seed, config)) = data.split_first_chunk::<8>() else {
        return;
    };
    let Some(model) = small_model(config) else {
        return;
    };
    let steps = model.steps.unwrap_or(MAX_STEPS).min(MAX_STEPS);
    let mut inputs = match InputStream::open(&model, None) {
        Ok(inputs) => inputs,
        Err(e) => return check_message(&e),
    };
    let (n, q) = (model.dims.n, model.dims.q);
    let mut truth = CsvWriter::new(Vec::new(), &StepLayout::truth(n).header()).expect("memory");
    let mut meas =
        CsvWriter::new(Vec::new(), &StepLayout::measurements(q).header()).expect("memory");
    let seed = u64::from_le_bytes(*seed);
    let result = sisfilt::simulate::simulate(&model, steps, seed, &mut inputs, |s| {
        let finite = s.x.iter().chain(s.y).chain(s.u).all(|v| v.is_finite());
        assert!(finite, "t = {}: not finite", s.t);
        for i in 0..model.subsystems {
            let gamma = Some(u8::from(s.gamma[i]));
            truth
                .row(s.t, i + 1, &s.x[i * n..(i + 1) * n], gamma)
                .expect("memory");
            meas.row(s.t, i + 1, &s.y[i * q..(i + 1) * q], None)
                .expect("memory");
        }
        Ok(())
    });
    if let Err(e) = result {
        check_message(&e);
    }
});

//! Config parser and validator on arbitrary UTF-8: `ConfigSource::from_text` then
//! `Model::from_config` (and, for small valid chains, the step-1 solver that `check` and
//! `simulate` build) must never panic, and every error must be one line naming the file.
#![no_main]

use std::path::PathBuf;

use libfuzzer_sys::fuzz_target;
use sisfilt::config::ConfigSource;
use sisfilt::interconnect::ChainSolver;
use sisfilt::model::Model;

const NAME: &str = "fuzz.toml";

fn check_message(err: &sisfilt::Error) {
    let msg = err.to_string();
    assert!(!msg.contains('\n'), "multi-line error: {msg:?}");
    assert!(
        msg.starts_with(NAME),
        "error does not name the file: {msg:?}"
    );
}

fuzz_target!(|data: &[u8]| {
    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    let src = match ConfigSource::from_text(NAME, PathBuf::from("."), text.to_string()) {
        Ok(src) => src,
        Err(e) => return check_message(&e),
    };
    let model = match Model::from_config(&src) {
        Ok(model) => model,
        Err(e) => return check_message(&e),
    };
    // Exercise what the commands read next, on chains small enough to stay fast.
    let d = model.dims;
    if model.subsystems * (d.s() + d.n) <= 10_000 {
        for w in model.windows().iter().take(4) {
            if let Err(e) = ChainSolver::new(&model, w.first) {
                check_message(&e);
            }
            for i in 1..=model.subsystems.min(8) {
                let _ = model.params(w.first, i);
                let p = model.p(w.first, i);
                assert!((0.0..=1.0).contains(&p), "p = {p}");
            }
        }
    }
});

//! What the `estimate` and `simulate` targets share: a fuzzed config read and checked as the
//! commands read it, kept when its chain is small.

use std::path::PathBuf;

use sisfilt::config::ConfigSource;
use sisfilt::inputs::InputStream;
use sisfilt::model::Model;

/// Chains at most this large (`N·n`), so that each input runs in milliseconds.
pub const MAX_LIFTED: usize = 24;

/// An error must be one line.
pub fn check_message(err: &sisfilt::Error) {
    let msg = err.to_string();
    assert!(!msg.contains('\n'), "multi-line error: {msg:?}");
}

/// The model of the config `text`, when it is valid UTF-8, reads and checks, has at most
/// [`MAX_LIFTED`] lifted states and generates its inputs (an inputs file would be read from
/// the fuzzer's folder); every error on the way must be one line.
pub fn small_model(text: &[u8]) -> Option<Model> {
    let text = std::str::from_utf8(text).ok()?;
    let src = ConfigSource::from_text("fuzz.toml", PathBuf::from("."), text.to_string())
        .map_err(|e| check_message(&e))
        .ok()?;
    // The model's own arrays grow with N: decide before building it.
    if !(1..=MAX_LIFTED as i64).contains(&src.raw.subsystems) {
        return None;
    }
    let model = Model::from_config(&src)
        .map_err(|e| check_message(&e))
        .ok()?;
    let small = model.subsystems * model.dims.n <= MAX_LIFTED;
    (small && InputStream::path(&model, None).is_none()).then_some(model)
}

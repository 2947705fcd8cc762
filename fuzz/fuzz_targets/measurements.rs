//! The streaming CSV reader on arbitrary bytes, with the layout of a measurement file
//! (`t,i,y1,y2`, N = 3): it must never panic, only hand out finite numbers (or NaN for an
//! empty cell when empty cells are allowed), and every error must be one line naming the file.
#![no_main]

use libfuzzer_sys::fuzz_target;
use sisfilt::io::{StepLayout, StepReader};

const NAME: &str = "fuzz.csv";
const SUBSYSTEMS: usize = 3;

fn check_message(err: &sisfilt::Error) {
    let msg = err.to_string();
    assert!(!msg.contains('\n'), "multi-line error: {msg:?}");
    assert!(
        msg.starts_with(NAME),
        "error does not name the file: {msg:?}"
    );
}

fuzz_target!(|data: &[u8]| {
    // The first byte says whether empty cells are allowed (`--dropouts known`).
    let Some((&mode, bytes)) = data.split_first() else {
        return;
    };
    let allow_empty = mode & 1 == 1;
    let layout = StepLayout {
        allow_empty,
        ..StepLayout::measurements(2)
    };
    let mut reader = match StepReader::new(NAME, bytes, layout, SUBSYSTEMS) {
        Ok(r) => r,
        Err(e) => return check_message(&e),
    };
    let mut y = vec![0.0; reader.row_values()];
    let mut expected_t = 1;
    loop {
        match reader.read_step(&mut y) {
            Ok(Some(t)) => {
                assert_eq!(t, expected_t);
                expected_t += 1;
                for v in &y {
                    assert!(v.is_finite() || (allow_empty && v.is_nan()), "value {v}");
                }
            }
            Ok(None) => break,
            Err(e) => return check_message(&e),
        }
    }
});

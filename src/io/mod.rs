//! Files: the streaming CSV reader and writer of docs/theory.md §13, atomic output files, the check that
//! no output is an input, and the `run.json` record that `simulate` leaves beside its data.

pub mod csv_in;
pub mod csv_out;
pub mod estimates;
pub mod files;
pub mod json_number;
pub mod output;
pub mod run_record;

pub use csv_in::{LineLimit, StepLayout, StepReader};
pub use csv_out::CsvWriter;
pub use files::{Role, check_files, folder_of};
pub use output::{Output, remove_pending_files};
pub use run_record::RunRecord;

use std::io::Read;

use crate::error::{Error, Result};

/// The largest JSON document read whole (an `evaluate` output, a part, a run record, a figure's
/// standard input): an evaluation of 10⁵ steps with every filter holds about 20 MB.
pub const MAX_DOCUMENT_BYTES: u64 = 256 << 20;

/// The bytes of the input `name` from `source`, refused above `max_bytes` (a file of
/// gigabytes, `/dev/zero`) before they are held whole; `beyond` says in the message what the
/// limit is (`the largest config read`).
pub fn read_bytes(name: &str, source: impl Read, max_bytes: u64, beyond: &str) -> Result<Vec<u8>> {
    let mut bytes = Vec::new();
    source
        .take(max_bytes + 1)
        .read_to_end(&mut bytes)
        .map_err(|e| Error::read(name, e))?;
    if bytes.len() as u64 > max_bytes {
        return Err(Error::File {
            file: name.to_string(),
            msg: format!(
                "larger than {}, {beyond}",
                crate::memory::human_bytes(max_bytes)
            ),
        });
    }
    Ok(bytes)
}

/// [`read_bytes`] of a text; `what` names the kind of file in the message.
pub fn read_text(name: &str, source: impl Read, max_bytes: u64, what: &str) -> Result<String> {
    let bytes = read_bytes(name, source, max_bytes, &format!("the largest {what} read"))?;
    String::from_utf8(bytes).map_err(|_| {
        let err = std::io::Error::new(
            std::io::ErrorKind::InvalidData,
            "stream did not contain valid UTF-8",
        );
        Error::read(name, err)
    })
}

//! Files: the streaming CSV reader and writer of docs/theory.md §13, atomic output files, the check that
//! no output is an input, and the `run.json` record that `simulate` leaves beside its data.

pub mod csv_in;
pub mod csv_out;
pub mod estimates;
pub mod files;
pub mod json_number;
pub mod output;
pub mod run_record;

pub use csv_in::{StepLayout, StepReader};
pub use csv_out::CsvWriter;
pub use files::{Role, check_files, folder_of};
pub use output::{Output, remove_pending_files};
pub use run_record::RunRecord;

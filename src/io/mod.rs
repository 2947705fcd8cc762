//! Files: the streaming CSV reader and writer of SPEC §6, atomic output files, and the
//! `run.json` record that `simulate` leaves beside its data.

pub mod csv_in;
pub mod csv_out;
pub mod estimates;
pub mod output;
pub mod run_record;

pub use csv_in::{StepLayout, StepReader};
pub use csv_out::CsvWriter;
pub use output::{Output, remove_pending_files};
pub use run_record::RunRecord;

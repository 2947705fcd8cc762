//! A whole run, as every front end makes it (docs/theory.md §13): a [`RunSpec`] checked once
//! into a [`CheckedSpec`], which builds the filter or smoother it describes.

pub mod spec;

pub use spec::{CheckedSpec, RunSpec, Setting, SpecError, check_update};

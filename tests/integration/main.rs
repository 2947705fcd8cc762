//! The integration tests, one binary with a module per area (linked once), sharing the
//! fixtures of [`common`]. `tests/allocation.rs` stays a binary of its own: its counting
//! global allocator would count the allocations of every test running beside it.

// Index loops mirror the formulas of docs/theory.md, as in the library.
#![allow(clippy::needless_range_loop)]

mod common;

mod bad_inputs;
mod band;
mod check_cli;
mod config_errors;
mod config_forms;
mod estimate_cli;
mod estimator;
mod evaluate_cli;
mod fit;
mod fit_band;
mod fit_each;
mod flags;
mod gaps;
mod hold_out;
mod initial;
mod innovations;
mod joint_filter;
mod noise_score;
mod plot_cli;
mod properties;
mod python_files;
mod python_package;
mod real_data;
mod reference_filters;
mod run_api;
mod settings;
mod shards;
mod simulate_cli;
mod smoother;
mod stability;
mod verdict;

//! The command line: everything that knows clap. `main.rs` parses a [`Cli`] and hands its
//! command to [`run`]; each command turns its arguments into library calls and reports on
//! standard error through [`sisfilt::messages`].
//!
//! - [`check`], [`simulate`], [`estimate`], [`fit`], [`evaluate`], [`plot`], [`completions`],
//!   [`man`]:
//!   one file per command, each with its arguments (the doc comments are the `--help` text).
//! - [`choice`]: the library's named options ([`sisfilt::choice::Choice`]) as clap values.

mod check;
mod choice;
mod completions;
mod data;
mod estimate;
mod evaluate;
mod fit;
mod man;
mod plot;
mod simulate;

use std::io::Write;
use std::path::{Path, PathBuf};

use anyhow::Result;
use clap::{Parser, Subcommand};

use sisfilt::config::ConfigSetting;
use sisfilt::error::Error;
use sisfilt::evaluate::EvaluateError;
use sisfilt::fit::FitError;
use sisfilt::inputs::InputStream;
use sisfilt::io::{Output, Role};
use sisfilt::memory::human_bytes;
use sisfilt::model::Model;
use sisfilt::run::{RunError, Setting, SpecError};

/// Distributed state estimation for chains of interconnected subsystems whose sensors drop
/// measurements at random (two-step filter of Bai Li's paper, with the corrections of docs/theory.md §6).
#[derive(Debug, Parser)]
#[command(name = "sisfilt", version, about, long_about = None)]
pub struct Cli {
    /// Print no warnings or progress bars on standard error (errors are still printed).
    #[arg(
        long,
        short,
        global = true,
        conflicts_with = "verbose",
        display_order = 1000
    )]
    pub quiet: bool,
    /// Also print progress and timings on standard error (`info: ` lines).
    #[arg(long, short, global = true, display_order = 1000)]
    pub verbose: bool,
    #[command(subcommand)]
    pub command: Command,
}

impl Cli {
    /// The verbosity asked for by `--quiet` / `--verbose`.
    pub fn verbosity(&self) -> sisfilt::messages::Verbosity {
        use sisfilt::messages::Verbosity;
        match (self.quiet, self.verbose) {
            (true, _) => Verbosity::Quiet,
            (false, true) => Verbosity::Verbose,
            (false, false) => Verbosity::Normal,
        }
    }
}

/// `--set KEY=VALUE`: config values over the file's, for every command that reads a config.
#[derive(Debug, Clone, clap::Args)]
pub struct SetArgs {
    /// Set a config value over the file's: the key by its dotted path, the value in TOML
    /// syntax (repeatable, the last wins), e.g. --set dropout.p=0.7 --set 'model.M=[[0.02]]'
    /// --set 'override[1].p=0.3'. Checked as the file is; recorded in run.json and the
    /// estimates' metadata.
    #[arg(long = "set", value_name = "KEY=VALUE")]
    pub set: Vec<ConfigSetting>,
}

#[derive(Debug, Subcommand)]
pub enum Command {
    /// Validate a config and print its dimensions, which parameters vary, the interconnection
    /// system's condition estimate and the spectral radius of the lifted A_eff.
    Check {
        /// The TOML config.
        config: PathBuf,
        #[command(flatten)]
        set: SetArgs,
    },
    /// Simulate the chain with random dropouts; write truth.csv, measurements.csv, inputs.csv
    /// (when there are inputs) and run.json into --out.
    Simulate(simulate::SimulateArgs),
    /// Run the filter on a measurement file and write x̂(t|t) with P(t|t) for every (t, i).
    Estimate(estimate::EstimateArgs),
    /// Fit the arrival probability p and the diagonals of Q and M to a measurement file by
    /// maximum likelihood, with 95 % intervals; optionally write the fitted config.
    Fit(fit::FitArgs),
    /// Monte Carlo comparison of the distributed filter with the paper's version, the joint
    /// band-k filter, the optimal centralized filter, a filter that knows the dropouts and a
    /// naive one.
    Evaluate(evaluate::EvaluateArgs),
    /// Add up the parts of a sharded study (`evaluate --shard K/M --out PART`) into the table
    /// and JSON that one `evaluate` of the whole study gives.
    EvaluateMerge(evaluate::MergeArgs),
    /// Draw an SVG figure from the files the other commands write.
    #[command(subcommand)]
    Plot(plot::PlotCommand),
    /// Print a shell completion script to standard output, e.g.
    /// `sisfilt completions bash > ~/.local/share/bash-completion/completions/sisfilt`.
    Completions {
        /// The shell.
        #[arg(value_enum)]
        shell: clap_complete::Shell,
    },
    /// Print a man page (roff) to standard output, e.g. `sisfilt man | man -l -`.
    Man {
        /// The command whose page to print, e.g. `estimate` or `plot series` (default: the
        /// page of `sisfilt` itself).
        command: Vec<String>,
    },
}

/// Runs one command.
pub fn run(command: Command) -> Result<()> {
    match command {
        Command::Check { config, set } => check::run(&config, &set.set),
        Command::Simulate(args) => simulate::run(&args),
        Command::Estimate(args) => on_pool(|| estimate::run(&args)),
        Command::Fit(args) => on_pool(|| fit::run(&args)),
        Command::Evaluate(args) => on_pool(|| evaluate::run(&args)),
        Command::EvaluateMerge(args) => evaluate::merge(&args),
        Command::Plot(command) => plot::run(command),
        Command::Completions { shell } => completions::run(shell),
        Command::Man { command } => man::run(&command),
    }
}

/// Runs a command that filters (in parallel loops) with this thread as the first worker of
/// rayon's pool: the loops start from inside the pool instead of waking it from outside each
/// time, and the pool starts one thread fewer (no hand-over of the command to another).
fn on_pool(command: impl FnOnce() -> Result<()>) -> Result<()> {
    // Refused only once the pool exists, which a command's first loop would have made.
    let _ = rayon::ThreadPoolBuilder::new()
        .use_current_thread()
        .build_global();
    command()
}

/// Writes `text` to standard output; a closed pipe comes back as an [`Error::Io`] of kind
/// `BrokenPipe`, which the binary ends quietly with exit 0 (`println!` would panic instead).
fn print_stdout(text: &[u8]) -> Result<()> {
    let mut out = Output::create(Path::new("-"))?;
    out.write_all(text).map_err(|e| Error::io("<stdout>", e))?;
    out.commit()?;
    Ok(())
}

/// Writes `text` and a line break to standard output (see [`print_stdout`]).
fn print_line(text: &str) -> Result<()> {
    print_stdout(format!("{text}\n").as_bytes())
}

/// The files a run of `model` reads: its config, and the inputs file the config names.
fn config_files<'a>(config: &'a Path, model: &'a Model) -> Vec<Role<'a>> {
    let mut read = vec![Role::new("the config", config)];
    if let Some(path) = InputStream::path(model, None) {
        read.push(Role::new("the inputs file", path));
    }
    read
}

/// A library error in the command line's words: a [`SpecError`], a [`RunError`] or an
/// [`EvaluateError`] names the flags of its settings; every other error is left as it is.
fn in_flag_words(e: impl Into<Error>) -> Error {
    let flag = |setting: Setting| match setting {
        Setting::Band => "--band",
        Setting::BandTol => "--band-tol",
        Setting::Loading => "--loading",
        Setting::SecondMomentBand => "--second-moment band",
    };
    Error::Usage(match e.into() {
        Error::Spec(SpecError::MixtureWithKnownDropouts) => "--update mixture detects lost measurements; with --dropouts known there is nothing to detect: leave one of them out".into(),
        Error::Spec(SpecError::JointOnly(setting)) => {
            format!("{} belongs to the joint filter; add --filter joint", flag(setting))
        }
        Error::Spec(SpecError::PaperMomentInJoint) => "--second-moment paper belongs to the distributed filter; the joint filter takes band, lifted or local".into(),
        Error::Spec(SpecError::SmoothAndPredicted) => "--smooth and --predicted exclude each other".into(),
        Error::Spec(SpecError::HoldOutShare(share)) => {
            format!("--hold-out {share}: expected a share above 0 and below 1")
        }
        Error::Spec(SpecError::HoldOutPredicted) => "--hold-out and --predicted exclude each other: held-out readings are scored against the estimate of their own step, and row t of --predicted is that of t + 1".into(),
        Error::Spec(SpecError::NotFiniteNonNegative { setting, value }) => {
            format!("{} {value}: expected a finite number ≥ 0", flag(setting))
        }
        Error::Run(RunError::OverMaxMemory { t, need, limit }) => format!(
            "--smooth: the stored forward pass needs {} by t = {t} ({need} bytes), above --max-memory {} ({limit} bytes); raise --max-memory, or smooth a shorter file",
            human_bytes(need),
            human_bytes(limit)
        ),
        Error::OverMemory { what, need, limit } => format!(
            "{what} needs {} ({need} bytes), above --max-memory {} ({limit} bytes); raise --max-memory",
            human_bytes(need),
            human_bytes(limit)
        ),
        Error::Evaluate(EvaluateError::NoRuns) => "--runs must be at least 1".into(),
        Error::Evaluate(EvaluateError::NothingAfterBurnIn {
            burn_in,
            config,
            steps,
        }) => format!(
            "--burn-in {burn_in} leaves no step to score: {config} has T = {steps} steps; choose a burn-in below T"
        ),
        Error::Evaluate(EvaluateError::TrueP(p)) => {
            format!("--true-p: expected a probability in [0, 1], found {p}")
        }
        Error::Evaluate(EvaluateError::EmptySweep) => "--sweep-p: expected at least one value".into(),
        Error::Evaluate(EvaluateError::MoreShardsThanRuns { count, runs }) => format!(
            "--shard K/{count} with --runs {runs}: expected at most one shard per run; use fewer shards or more runs"
        ),
        Error::Evaluate(EvaluateError::SweepP(p)) => {
            format!("--sweep-p: expected probabilities in [0, 1], found {p}")
        }
        e @ Error::TransferSolver { .. } => format!("{e}; use --solver banded"),
        Error::Fit(FitError::UnknownParameter(name)) => {
            format!("--params: unknown parameter `{name}`: expected a list of p, Q, M, Q[i] and M[i]")
        }
        Error::Fit(e @ (FitError::SharedAndEach(_) | FitError::EachVariesInTime(_))) => {
            format!("--{e}")
        }
        Error::Fit(FitError::NoParameters) => "--params: expected at least one of p, Q and M".into(),
        Error::Fit(FitError::DistributedQ) => "--filter distributed cannot fit Q: its log-likelihood ignores the uncertainty of the neighbours' states, which Q then absorbs (docs/theory.md §16); use --filter joint or centralized, or leave Q out of --params".into(),
        Error::Fit(FitError::PWithKnownDropouts) => "--dropouts known: p does not enter the likelihood of the measurements received (the lost ones are given); leave p out of --params, or fit with --dropouts unknown".into(),
        Error::Fit(FitError::NoIterations) => "--max-iter: expected at least 1".into(),
        Error::Run(RunError::NothingScored) => "--truth: no step could be scored (with --predicted, row t is scored against the truth at t + 1, and the measurements hold one step)".into(),
        other => return other,
    })
}

//! Command-line definitions (clap derive). The doc comments are the `--help` text; the
//! commands themselves live in [`crate::commands`].

use std::path::PathBuf;

use clap::{Parser, Subcommand};

use crate::filter::{Dropouts, InterconnectFrom, SecondMoment};
use crate::interconnect::SolverKind;
use crate::io::estimates::Format;

/// Distributed state estimation for chains of interconnected subsystems whose sensors drop
/// measurements at random (two-step filter of Bai Li's paper, with the corrections of SPEC §8).
#[derive(Debug, Parser)]
#[command(name = "sisfilt", version, about, long_about = None)]
pub struct Cli {
    #[command(subcommand)]
    pub command: Command,
}

#[derive(Debug, Subcommand)]
pub enum Command {
    /// Validate a config and print its dimensions, which parameters vary, the interconnection
    /// system's condition estimate and the spectral radius of the lifted A_eff.
    Check {
        /// The TOML config.
        config: PathBuf,
    },
    /// Simulate the chain with random dropouts; write truth.csv, measurements.csv, inputs.csv
    /// (when there are inputs) and run.json into --out.
    Simulate(SimulateArgs),
    /// Run the filter on a measurement file and write x̂(t|t) with P(t|t) for every (t, i).
    Estimate(EstimateArgs),
    /// Monte Carlo comparison of the distributed filter with the paper's version, the optimal
    /// centralized filter, a filter that knows the dropouts and a naive one.
    Evaluate(EvaluateArgs),
}

#[derive(Debug, clap::Args)]
pub struct EvaluateArgs {
    /// The TOML config.
    pub config: PathBuf,
    /// Number of independent realisations.
    #[arg(long)]
    pub runs: usize,
    /// Seed of the first run; run r uses seed + r (default: the config's `seed`).
    #[arg(long)]
    pub seed: Option<u64>,
    /// Write the results as JSON to this file.
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Leave the steps t ≤ BURN_IN out of the figures (the initial transient).
    #[arg(long, default_value_t = 0)]
    pub burn_in: usize,
    /// Largest lifted state size N·n for the centralized filters (skipped above it).
    #[arg(long, default_value_t = crate::filter::centralized::DEFAULT_MAX_LIFTED)]
    pub max_lifted: usize,
}

/// The filters `estimate` can run.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum FilterKind {
    /// The two-step distributed filter of the paper (SPEC §2–§3).
    Distributed,
    /// The optimal linear filter on the lifted system (SPEC §5): O((N·n)³) per step, a
    /// yardstick; ignores --solver, --second-moment and --interconnect-from.
    Centralized,
}

#[derive(Debug, clap::Args)]
pub struct EstimateArgs {
    /// The TOML config. May be left out when --meas was written by `simulate`: the config
    /// recorded in run.json beside it is used.
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Measurement CSV (`t,i,y1..yq`), or - for standard input.
    #[arg(long)]
    pub meas: PathBuf,
    /// Inputs CSV (`t,i,u1..um`); default: inputs.csv beside a simulated --meas, else the
    /// config's [input].
    #[arg(long)]
    pub inputs: Option<PathBuf>,
    /// Output file, or - for standard output.
    #[arg(long, default_value = "-")]
    pub out: PathBuf,
    /// Output format (default: json when --out ends in .json, else csv).
    #[arg(long, value_enum)]
    pub format: Option<Format>,
    /// Which filter to run.
    #[arg(long, value_enum, default_value_t = FilterKind::Distributed)]
    pub filter: FilterKind,
    /// Step-1 solver [default: banded; transfer with --paper].
    #[arg(long, value_enum)]
    pub solver: Option<SolverKind>,
    /// Second moment S = E[x xᵀ] in the Nahi filter [default: local; paper with --paper].
    #[arg(long, value_enum)]
    pub second_moment: Option<SecondMoment>,
    /// Estimate fed to step 1 [default: filtered; predicted with --paper].
    #[arg(long, value_enum)]
    pub interconnect_from: Option<InterconnectFrom>,
    /// unknown: lost measurements look like noise (the paper's model); known: lost elements
    /// are empty cells and are skipped.
    #[arg(long, value_enum, default_value_t = Dropouts::Unknown)]
    pub dropouts: Dropouts,
    /// Exactly the paper's algorithm: --solver transfer --interconnect-from predicted
    /// --second-moment paper (explicit options win).
    #[arg(long)]
    pub paper: bool,
    /// Write x̂(t+1|t) with T(t+1) on row t instead of x̂(t|t), P(t|t).
    #[arg(long)]
    pub predicted: bool,
    /// Truth CSV (`t,i,x1..xn,gamma`): report RMSE per state element and average NEES.
    #[arg(long)]
    pub truth: Option<PathBuf>,
    /// Largest lifted state size N·n the centralized filter accepts.
    #[arg(long, default_value_t = crate::filter::centralized::DEFAULT_MAX_LIFTED)]
    pub max_lifted: usize,
    /// Print on standard error the wall-clock time spent reading the input files, filtering
    /// and handing the estimates to the writer thread, and the time that thread spent
    /// formatting and writing them (a `timings:` line).
    #[arg(long)]
    pub timings: bool,
}

#[derive(Debug, clap::Args)]
pub struct SimulateArgs {
    /// The TOML config.
    pub config: PathBuf,
    /// Output folder, created when missing.
    #[arg(long, default_value = ".")]
    pub out: PathBuf,
    /// Seed of every random draw (default: the config's `seed`, else 0).
    #[arg(long)]
    pub seed: Option<u64>,
    /// Leave lost measurement elements empty in measurements.csv (for `--dropouts known`);
    /// by default they hold the noise R u + d, as in the paper's model.
    #[arg(long)]
    pub mark_missing: bool,
}

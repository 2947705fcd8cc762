//! Command-line definitions (clap derive). The doc comments are the `--help` text; the
//! commands themselves live in [`crate::commands`].

use std::path::PathBuf;

use clap::{Parser, Subcommand};

use crate::filter::{Dropouts, InterconnectFrom, SecondMoment};
use crate::interconnect::SolverKind;
use crate::io::estimates::Format;

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
    pub fn verbosity(&self) -> crate::messages::Verbosity {
        use crate::messages::Verbosity;
        match (self.quiet, self.verbose) {
            (true, _) => Verbosity::Quiet,
            (false, true) => Verbosity::Verbose,
            (false, false) => Verbosity::Normal,
        }
    }
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
    /// Monte Carlo comparison of the distributed filter with the paper's version, the joint
    /// band-k filter, the optimal centralized filter, a filter that knows the dropouts and a
    /// naive one.
    Evaluate(EvaluateArgs),
    /// Draw an SVG figure from the files the other commands write.
    #[command(subcommand)]
    Plot(PlotCommand),
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

/// The figures of `sisfilt plot` (docs/theory.md §13); each writes one SVG file.
#[derive(Debug, Subcommand)]
pub enum PlotCommand {
    /// One state element of one subsystem against time: truth, estimate with its ±2σ band,
    /// measurements and the steps whose measurement was lost; below, the estimation error.
    Series(PlotSeriesArgs),
    /// Time × subsystem map of the normalised error |x̂ − x| / σ of one state element (or the
    /// plain error |x̂ − x| with --plain): how errors spread along the chain.
    Heatmap(PlotHeatmapArgs),
    /// RMSE and average NEES of each filter from `sisfilt evaluate --out` (curves against p
    /// for `evaluate --sweep-p`).
    Evaluate(PlotEvaluateArgs),
}

#[derive(Debug, clap::Args)]
pub struct PlotSeriesArgs {
    /// Estimates file written by `sisfilt estimate` (CSV or JSON).
    #[arg(long)]
    pub estimates: PathBuf,
    /// Truth CSV written by `sisfilt simulate` (`t,i,x1..xn,gamma`).
    #[arg(long)]
    pub truth: PathBuf,
    /// Measurement CSV (`t,i,y1..yq`): drawn over the state when a row of J picks that state
    /// alone, else in a panel of its own.
    #[arg(long)]
    pub meas: Option<PathBuf>,
    /// A second estimates file (e.g. from `estimate --smooth`), drawn with its own band for
    /// comparison.
    #[arg(long)]
    pub smoothed: Option<PathBuf>,
    /// The config, to learn J (default: the run.json beside --meas or --truth).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// The subsystem i (1..N).
    #[arg(long)]
    pub subsystem: usize,
    /// The state element k (1..n).
    #[arg(long)]
    pub state: usize,
    /// The SVG file to write.
    #[arg(long)]
    pub out: PathBuf,
}

#[derive(Debug, clap::Args)]
pub struct PlotHeatmapArgs {
    /// Estimates file written by `sisfilt estimate` (CSV or JSON).
    #[arg(long)]
    pub estimates: PathBuf,
    /// Truth CSV written by `sisfilt simulate`.
    #[arg(long)]
    pub truth: PathBuf,
    /// The state element k (1..n).
    #[arg(long, default_value_t = 1)]
    pub state: usize,
    /// Map the plain error |x̂ − x| instead of |x̂ − x| / σ.
    #[arg(long)]
    pub plain: bool,
    /// The SVG file to write.
    #[arg(long)]
    pub out: PathBuf,
}

#[derive(Debug, clap::Args)]
pub struct PlotEvaluateArgs {
    /// JSON written by `sisfilt evaluate --out` (with or without --sweep-p).
    #[arg(long)]
    pub input: PathBuf,
    /// The SVG file to write.
    #[arg(long)]
    pub out: PathBuf,
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
    /// The joint filter's covariance band K.
    #[arg(long, value_name = "K", default_value_t = crate::filter::joint::DEFAULT_BAND)]
    pub band: usize,
    /// Run only these filters (comma-separated; default: all): distributed,
    /// distributed-paper, joint, centralized, centralized-known, naive, and the smoothers
    /// distributed-smoother, joint-smoother, centralized-smoother.
    #[arg(long, value_delimiter = ',', value_name = "NAMES")]
    pub filters: Vec<String>,
    /// Also run the smoothers of docs/theory.md §9 (distributed-smoother, joint-smoother,
    /// centralized-smoother); their RMSE ratio is to the centralized smoother.
    #[arg(long)]
    pub smooth: bool,
    /// Repeat the evaluation for each arrival probability in this comma-separated list (e.g.
    /// 0.5,0.7,0.9), which replaces the config's p everywhere (`[dropout]` and overrides); the
    /// same seeds serve every value.
    #[arg(long, value_delimiter = ',')]
    pub sweep_p: Option<Vec<f64>>,
}

/// The filters `estimate` can run.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum FilterKind {
    /// The two-step distributed filter of the paper (docs/theory.md §2, §4).
    Distributed,
    /// The optimal linear filter on the lifted system (docs/theory.md §7): O((N·n)³) per step, a
    /// yardstick; ignores --solver, --second-moment and --interconnect-from.
    Centralized,
    /// The joint band-k filter (docs/theory.md §8): the lifted covariance on a band of width --band,
    /// honest covariances and near-optimal accuracy at a cost linear in N; ignores --solver
    /// and --interconnect-from.
    Joint,
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
    /// config's input table.
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
    /// Second moment S = E[x xᵀ] in the Nahi filter [default: local; paper with --paper;
    /// band for --filter joint].
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
    /// Write the smoothed x̂(t|T) with P(t|T), from every measurement of the file, instead of
    /// the filtered estimates (docs/theory.md §9): per-subsystem RTS for distributed, RTS for
    /// centralized, the information form for joint.
    #[arg(long, conflicts_with = "predicted")]
    pub smooth: bool,
    /// Largest memory the smoother's stored forward pass may take: bytes, or with a K, M or G
    /// suffix [default: 8G].
    #[arg(long, value_name = "BYTES", value_parser = parse_max_memory)]
    pub max_memory: Option<u64>,
    /// Joint filter: keep the covariance blocks |i − j| ≤ K [default: 2].
    #[arg(long, value_name = "K")]
    pub band: Option<usize>,
    /// Joint filter: relative size below which blocks of A_eff are dropped [default: 1e-9].
    #[arg(long, value_name = "TOL")]
    pub band_tol: Option<f64>,
    /// Joint filter: diagonal loading ε of the prior band, P_ii += ε tr(P_ii)/n I
    /// [default: 1e-9 when every Q is zero, else 0].
    #[arg(long, value_name = "EPS")]
    pub loading: Option<f64>,
    /// Print on standard error the wall-clock time spent reading the input files, filtering
    /// and handing the estimates to the writer thread, and the time that thread spent
    /// formatting and writing them (a `timings:` line).
    #[arg(long)]
    pub timings: bool,
}

fn parse_max_memory(text: &str) -> Result<u64, String> {
    crate::smoother::parse_bytes(text)
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

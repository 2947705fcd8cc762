//! `sisfilt plot`: SVG figures from the files the other commands write (the drawing is
//! [`sisfilt::plot`]'s).

use std::path::PathBuf;

use anyhow::Result;
use clap::Subcommand;

use sisfilt::plot::heatmap::HeatmapPlot;
use sisfilt::plot::series::SeriesPlot;

use super::SetArgs;

/// The figures of `sisfilt plot` (docs/theory.md §13); each writes one SVG file.
#[derive(Debug, Subcommand)]
pub enum PlotCommand {
    /// One state element of one subsystem against time: truth, estimate with its ±2σ band,
    /// measurements and the steps whose measurement was lost; below, the estimation error.
    /// Without --truth, the estimate, its band and the measurements; below, the NIS of each
    /// measurement with its band (from the estimates' nis column, estimate --nis).
    Series(PlotSeriesArgs),
    /// Time × subsystem map of the normalised error |x̂ − x| / σ of one state element (or the
    /// plain error |x̂ − x| with --plain): how errors spread along the chain. Without --truth,
    /// the map of √NIS from the estimates' nis column (estimate --nis): a faulty sensor shows
    /// as a stripe.
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
    /// Truth CSV written by `sisfilt simulate` (`t,i,x1..xn,gamma`); without it the second
    /// panel shows the NIS (estimate --nis) instead of the error.
    #[arg(long)]
    pub truth: Option<PathBuf>,
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
    #[command(flatten)]
    pub set: SetArgs,
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
    /// Truth CSV written by `sisfilt simulate`; without it, the map shows each measurement's
    /// NIS (the estimates need the nis column of `estimate --nis`).
    #[arg(long)]
    pub truth: Option<PathBuf>,
    /// The state element k (1..n), with --truth.
    #[arg(long, default_value_t = 1)]
    pub state: usize,
    /// Map the plain error |x̂ − x| instead of |x̂ − x| / σ (with --truth).
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

/// Draws the figure of `command`.
pub fn run(command: PlotCommand) -> Result<()> {
    match command {
        PlotCommand::Series(a) => sisfilt::plot::series::run(&SeriesPlot {
            estimates: a.estimates,
            truth: a.truth,
            meas: a.meas,
            smoothed: a.smoothed,
            config: a.config,
            settings: a.set.set,
            subsystem: a.subsystem,
            state: a.state,
            out: a.out,
        }),
        PlotCommand::Heatmap(a) => sisfilt::plot::heatmap::run(&HeatmapPlot {
            estimates: a.estimates,
            truth: a.truth,
            state: a.state,
            plain: a.plain,
            out: a.out,
        }),
        PlotCommand::Evaluate(a) => sisfilt::plot::evaluate::run(&a.input, &a.out),
    }
}

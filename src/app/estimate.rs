//! `sisfilt estimate`: runs a filter (or smoother) over a measurement file and writes the
//! estimates `x̂` with their error covariances `P` (docs/theory.md §13).

use std::path::{Path, PathBuf};

use anyhow::Result;

use sisfilt::accuracy::AccuracyReport;
use sisfilt::config::{ConfigSource, RawConfig};
use sisfilt::error::Error;
use sisfilt::filter::{Dropouts, FilterKind, InterconnectFrom, SecondMoment, Update};
use sisfilt::inputs::{InputStream, open_csv};
use sisfilt::interconnect::{SolverKind, TRANSFER_ERROR_WARNING};
use sisfilt::io::estimates::{
    BackgroundWriter, EstimateKind, EstimatesMetadata, EstimatesSummary, EstimatesWriter, Format,
    RowValues,
};
use sisfilt::io::{Output, Role, RunRecord, StepLayout, check_files, folder_of};
use sisfilt::messages::{info, warn};
use sisfilt::run::{
    CheckedSpec, EstimateSink, FileSource, Note, ReadAhead, ReaderTruth, RunSpec, StepEstimates,
    StepSource, Timings, TruthSource,
};

use super::choice::choice;
use super::data::{Data, DataArgs};
use super::{SetArgs, in_flag_words};

#[derive(Debug, clap::Args)]
pub struct EstimateArgs {
    #[command(flatten)]
    pub data: DataArgs,
    /// Output file, or - for standard output.
    #[arg(long, default_value = "-")]
    pub out: PathBuf,
    /// Output format (default: json when --out ends in .json, else csv).
    #[arg(long, value_parser = choice::<Format>())]
    pub format: Option<Format>,
    /// Which filter to run.
    #[arg(long, value_parser = choice::<FilterKind>(), default_value = "distributed")]
    pub filter: FilterKind,
    /// Step-1 solver [default: banded; transfer with --paper].
    #[arg(long, value_parser = choice::<SolverKind>())]
    pub solver: Option<SolverKind>,
    /// Second moment S = E[x xᵀ] in the Nahi filter [default: local; paper with --paper;
    /// band for --filter joint]. No effect with --dropouts known or --update mixture,
    /// which need none.
    #[arg(long, value_parser = choice::<SecondMoment>())]
    pub second_moment: Option<SecondMoment>,
    /// Estimate fed to step 1 [default: filtered; predicted with --paper].
    #[arg(long, value_parser = choice::<InterconnectFrom>())]
    pub interconnect_from: Option<InterconnectFrom>,
    /// unknown: lost measurements look like noise (the paper's model), and an empty cell is a
    /// gap, a value not in the data; known: lost elements are empty cells. Either way empty
    /// cells are skipped.
    #[arg(long, value_parser = choice::<Dropouts>(), default_value = "unknown")]
    pub dropouts: Dropouts,
    /// How a measurement updates the estimate: linear is the paper's Nahi update; mixture
    /// weighs each measurement by the posterior probability that it arrived (the `arrival`
    /// column) and beats the best linear filter (docs/theory.md §10). Needs --dropouts unknown.
    #[arg(long, value_parser = choice::<Update>(), default_value = "linear")]
    pub update: Update,
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
    #[arg(long, default_value_t = sisfilt::filter::centralized::DEFAULT_MAX_LIFTED)]
    pub max_lifted: usize,
    /// Write the smoothed x̂(t|T) with P(t|T), from every measurement of the file, instead of
    /// the filtered estimates (docs/theory.md §9): per-subsystem RTS for distributed, RTS for
    /// centralized, the information form for joint.
    #[arg(long, conflicts_with = "predicted")]
    pub smooth: bool,
    /// Largest memory the run may hold, checked before each large array is allocated (the
    /// centralized filter's lifted matrices, the joint filter's bands, the smoother's stored
    /// forward pass): bytes, or with a K, M or G suffix [default: 8G].
    #[arg(long, value_name = "BYTES", value_parser = parse_max_memory)]
    pub max_memory: Option<u64>,
    /// Joint filter: keep the covariance blocks |i − j| ≤ K [default: 2].
    #[arg(long, value_name = "K")]
    pub band: Option<usize>,
    /// Joint filter: relative size below which blocks of A_eff are dropped [default: 1e-9].
    #[arg(long, value_name = "TOL")]
    pub band_tol: Option<f64>,
    /// Joint filter: diagonal loading ε of the prior band, P_ii += ε max(tr(P_ii)/n, f) I with
    /// a floor f far below any variance that matters (docs/theory.md §8) [default: 1e-9 when
    /// every Q is zero or the initial cov is singular, else 0]
    #[arg(long, value_name = "EPS")]
    pub loading: Option<f64>,
    /// Add the column `nis` (last): the normalised innovation squared of each measurement
    /// under the model, empty where nothing was received (docs/theory.md §14). The summary of
    /// the innovation check is printed on standard error (and kept in JSON) whatever.
    #[arg(long)]
    pub nis: bool,
    /// Print on standard error the wall-clock time spent reading the input files (waiting for
    /// them, when a thread reads them ahead), filtering, scoring the innovations and handing
    /// the estimates to the writer thread, and the time that thread spent formatting and
    /// writing them (a `timings:` line).
    #[arg(long)]
    pub timings: bool,
    /// Keep this share of the readings (0 < SHARE < 1, drawn at random) from the filter and
    /// score the estimates on them: their RMSE against that of linear interpolation in time,
    /// and whether the claimed variance is right (a `held out:` line; docs/theory.md §17).
    #[arg(long, value_name = "SHARE")]
    pub hold_out: Option<f64>,
    /// Seed of the draw of --hold-out.
    #[arg(long, default_value_t = 1, requires = "hold_out")]
    pub seed: u64,
    #[command(flatten)]
    pub set: SetArgs,
}

pub(super) fn parse_max_memory(text: &str) -> Result<u64, String> {
    sisfilt::memory::parse_bytes(text)
}

impl EstimateArgs {
    /// The run the arguments ask for, checked (docs/theory.md §13).
    fn spec(&self) -> Result<CheckedSpec> {
        let spec = RunSpec {
            filter: self.filter,
            update: self.update,
            dropouts: self.dropouts,
            paper: self.paper,
            solver: self.solver,
            second_moment: self.second_moment,
            interconnect_from: self.interconnect_from,
            band: self.band,
            band_tol: self.band_tol,
            loading: self.loading,
            smooth: self.smooth,
            predicted: self.predicted,
            max_lifted: self.max_lifted,
            max_memory: self.max_memory,
            nis_column: self.nis,
            hold_out: self.hold_out,
            hold_out_seed: self.seed,
        };
        Ok(spec.check().map_err(in_flag_words)?)
    }

    /// The output format: `--format`, else json when `--out` ends in `.json`, else csv.
    fn format(&self) -> Format {
        let json_name = self
            .out
            .extension()
            .is_some_and(|e| e.eq_ignore_ascii_case("json"));
        self.format
            .unwrap_or(if json_name { Format::Json } else { Format::Csv })
    }
}

/// The run record beside a data file, when there is one that reads (a record that does not
/// only costs the comparisons it serves).
fn record_beside(path: &Path) -> Option<RunRecord> {
    if path.as_os_str() == "-" {
        return None;
    }
    RunRecord::load(folder_of(path)).ok().flatten()
}

/// Whether two configs are the same tables (the settings applied).
fn same_config(a: &RawConfig, b: &RawConfig) -> bool {
    serde_json::to_value(a).ok() == serde_json::to_value(b).ok()
}

/// Warns when `--config` (its text, before `--set`) is not the config recorded beside
/// `--meas`.
fn warn_if_other_config(config: &Path, meas: &Path, src: &ConfigSource) {
    let Some(record) = record_beside(meas) else {
        return;
    };
    let file = ConfigSource::from_text(&src.name, src.dir.clone(), src.text.clone());
    if file.is_ok_and(|file| same_config(&record.config, &file.raw)) {
        return;
    }
    warn(format!(
        "--config {}: not the config that simulated --meas {} (the one its {} records): the estimates are of another model than the data's",
        config.display(),
        meas.display(),
        RunRecord::FILE
    ));
}

/// Warns when `--truth` and `--meas` come from different simulations: the run records beside
/// them differ in seed, horizon or config.
fn warn_if_other_truth(meas: &Path, truth: &Path) {
    let same_folder =
        |a: &Path, b: &Path| match (std::fs::canonicalize(a), std::fs::canonicalize(b)) {
            (Ok(a), Ok(b)) => a == b,
            _ => a == b,
        };
    if meas.as_os_str() == "-" || same_folder(folder_of(meas), folder_of(truth)) {
        return;
    }
    let (Some(m), Some(t)) = (record_beside(meas), record_beside(truth)) else {
        return;
    };
    let differs = [
        (m.seed != t.seed).then(|| format!("seed {} against {}", t.seed, m.seed)),
        (m.steps != t.steps).then(|| format!("T = {} against {}", t.steps, m.steps)),
        (!same_config(&m.config, &t.config)).then(|| "the config".to_string()),
    ];
    let differs: Vec<String> = differs.into_iter().flatten().collect();
    if !differs.is_empty() {
        warn(format!(
            "--truth {}: from another simulation than --meas {} (their {} files differ: {}): the accuracy figures compare unrelated runs",
            truth.display(),
            meas.display(),
            RunRecord::FILE,
            differs.join(", ")
        ));
    }
}

/// `sisfilt estimate`: the estimates of every `(t, i)`, written as they come (or, with
/// `--smooth`, after the backward pass).
pub fn run(args: &EstimateArgs) -> Result<()> {
    let started = std::time::Instant::now();
    let spec = args.spec()?;
    let data = args.data.load(&args.set.set)?;
    if let Some(path) = &args.data.config {
        warn_if_other_config(path, &args.data.meas, &data.src);
    }
    let Data {
        src,
        model,
        inputs_file,
        ..
    } = &data;
    let d = model.dims;
    let (n, big_n) = (d.n, model.subsystems);
    let mut read = args.data.roles(&data);
    if let Some(path) = &args.truth {
        warn_if_other_truth(&args.data.meas, path);
        read.push(Role::new("--truth", path));
    }
    check_files(&read, &[Role::new("--out", &args.out)])?;
    let inputs = InputStream::open(model, inputs_file.as_deref())?;
    let meas = open_csv(&args.data.meas, StepLayout::measurements(d.q), big_n)?;
    let truth = args
        .truth
        .as_ref()
        .map(|p| open_csv(p, StepLayout::truth(n), big_n))
        .transpose()?;
    // Open the output before the long run, so that a bad path fails fast.
    let output = Output::create(&args.out)?;
    let inputs_name = inputs_file.as_ref().map(|p| p.display().to_string());
    let metadata = EstimatesMetadata::new(
        src,
        model,
        spec.recorded(model),
        &args.data.meas.display().to_string(),
        inputs_name.as_deref(),
    );
    let out_name = output.name();
    // Filtered rows reach a waiting reader step by step; smoothed ones only at the end, when
    // the writer has the thread pool to itself.
    let smoothed = spec.output() == EstimateKind::Smoothed;
    let live = output.is_live() && !smoothed;
    let writer = EstimatesWriter::new(output, args.format(), spec.columns(model), Some(&metadata))
        .map_err(|e| Error::io(&out_name, e))?
        .live(live)
        .parallel(smoothed);
    if smoothed && !is_regular_file(&args.data.meas) {
        let name = match args.data.meas.as_os_str() == "-" {
            true => "standard input".to_string(),
            false => args.data.meas.display().to_string(),
        };
        warn(format!(
            "--smooth: {name} is a stream; the smoothed estimates need every step of it and come only once it ends (without --smooth, each step's estimates come as it arrives)"
        ));
    }
    let mut sink = WriterSink {
        writer: BackgroundWriter::new(writer, big_n),
        out_name,
    };
    let files = FileSource::new(meas, inputs);
    let mut source: Box<dyn StepSource> = match spec.reads_ahead() {
        // A stream is handed over step by step, as it comes.
        true => Box::new(ReadAhead::new(
            files,
            big_n * d.q,
            big_n * d.m,
            !is_regular_file(&args.data.meas),
        )),
        false => Box::new(files),
    };
    let mut truth = truth.map(ReaderTruth);
    let report = sisfilt::run::stream(
        model,
        &spec,
        source.as_mut(),
        truth.as_mut().map(|t| t as &mut dyn TruthSource),
        &mut sink,
    )
    .map_err(in_flag_words)?;
    let steps = report.steps;
    if !smoothed {
        let elapsed = started.elapsed().as_secs_f64();
        info(format!(
            "estimate: {steps} steps × {big_n} subsystems in {elapsed:.3} s ({:.3e} subsystem-steps/s)",
            (steps * big_n) as f64 / elapsed.max(1e-9)
        ));
        if let Some(loglik) = report.summary.loglik {
            info(format!(
                "log-likelihood of the measurements: {loglik:.6e} over {steps} steps"
            ));
        }
    }
    let mut timings = report.timings;
    let WriterSink { writer, out_name } = sink;
    let busy = timings.write(|| -> Result<f64> {
        let (writer, busy) = writer.finish().map_err(|e| Error::io(&out_name, e))?;
        writer.commit(&report.summary)?;
        Ok(busy)
    })?;
    report_summary(&report.summary);
    if args.timings && !smoothed {
        eprintln!(
            "timings: {}; the writer thread was busy {:.3} s",
            timings_summary(&timings, started.elapsed(), steps * big_n),
            busy
        );
    }
    Ok(())
}

/// Whether `path` is a regular file (not standard input, a pipe or a device).
fn is_regular_file(path: &std::path::Path) -> bool {
    path.as_os_str() != "-" && std::fs::metadata(path).is_ok_and(|m| m.is_file())
}

/// The estimates file of `estimate`, filled by a thread of its own as the run goes; the
/// run's notes are warnings.
struct WriterSink {
    writer: BackgroundWriter,
    out_name: String,
}

impl EstimateSink for WriterSink {
    fn step(&mut self, step: &StepEstimates<'_>) -> sisfilt::Result<()> {
        self.writer
            .write_step(
                step.t,
                step.x,
                step.p,
                step.band,
                RowValues {
                    arrival: step.arrival,
                    nis: Some(step.nis),
                },
            )
            .map_err(|e| Error::io(&self.out_name, e))
    }

    fn note(&mut self, note: Note) {
        warn(note_in_flag_words(&note));
    }
}

/// A run's note in the command line's words: the flags of the settings it names.
fn note_in_flag_words(note: &Note) -> String {
    match note {
        Note::OverconfidentDistributed => "Q = 0 on a coupled chain: the distributed filter treats the estimated interconnection signals as exact, so its reported covariance P is far too small (docs/theory.md §4); --filter joint keeps it honest (docs/theory.md §8)".into(),
        Note::OverconfidentDistributedSmoother => "Q = 0: the per-subsystem smoother trusts x(t+1) = A x + B v̂ exactly and can be worse than its own filter (docs/theory.md §9); --filter joint --smooth is the remedy".into(),
        Note::InaccurateTransfer { error, t } => format!(
            "the transfer solver's estimated relative error is {error:.1e} (> {TRANSFER_ERROR_WARNING:e}) from t = {t} on: its interconnection signals are inaccurate; use --solver banded"
        ),
        Note::Unstable { .. } | Note::Smoother(_) => note.to_string(),
    }
}

/// `read R s, filter F s, check C s, write W s, other O s, total X s, K rows, Y rows/s`
/// (`--timings`).
fn timings_summary(timings: &Timings, total: std::time::Duration, rows: usize) -> String {
    let secs = |d: std::time::Duration| d.as_secs_f64();
    let phases = [timings.read, timings.filter, timings.check, timings.write];
    let other = secs(total) - phases.into_iter().map(secs).sum::<f64>();
    format!(
        "read {:.3} s, filter {:.3} s, check {:.3} s, write {:.3} s, other {:.3} s, total {:.3} s, {rows} rows, {:.0} rows/s",
        secs(timings.read),
        secs(timings.filter),
        secs(timings.check),
        secs(timings.write),
        other.max(0.0),
        secs(total),
        rows as f64 / secs(total).max(1e-9)
    )
}

/// Prints the figures of a run on standard error: scored against the truth, the accuracy
/// (with the NEES warning of docs/theory.md §11) and the detection of lost measurements;
/// always, the innovation check with its verdict (docs/theory.md §14).
fn report_summary(summary: &EstimatesSummary) {
    if let Some(r) = &summary.accuracy {
        report_accuracy(r);
    }
    if let Some(d) = &summary.detection {
        sisfilt::messages::report("detection", d.summary());
    }
    if let Some(r) = &summary.held_out {
        sisfilt::messages::report("held out", r.summary());
    }
    if let Some(r) = &summary.innovations {
        sisfilt::messages::finding("innovations", r.summary());
        for line in r.warnings() {
            warn(line);
        }
    }
}

fn report_accuracy(r: &AccuracyReport) {
    sisfilt::messages::report("accuracy", r.summary());
    if r.nees_left_out > 0 {
        warn(format!(
            "NEES: {} of {} terms left out: error and claimed variance both below the resolution floor of f64 (docs/theory.md §11)",
            r.nees_left_out, r.terms
        ));
    }
    if r.nees_infinite > 0 {
        warn(format!(
            "NEES: {} terms have a resolved error against a zero claimed variance: the average NEES is infinite",
            r.nees_infinite
        ));
    }
}

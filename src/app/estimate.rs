//! `sisfilt estimate`: runs a filter (or smoother) over a measurement file and writes the
//! estimates `x̂` with their error covariances `P` (docs/theory.md §13).

use std::path::PathBuf;

use anyhow::Result;
use sha2::Digest;

use sisfilt::accuracy::{Accuracy, AccuracyReport, Detection};
use sisfilt::config::ConfigSource;
use sisfilt::error::Error;
use sisfilt::filter::{
    ChainFilter, Dropouts, FilterKind, InterconnectFrom, SecondMoment, Update, check_estimates,
};
use sisfilt::inputs::{InputStream, open_csv};
use sisfilt::interconnect::{SolverKind, TRANSFER_ERROR_WARNING};
use sisfilt::io::estimates::{
    BackgroundWriter, ConfigRef, EstimateKind, EstimatesColumns, EstimatesMetadata,
    EstimatesSummary, EstimatesWriter, Format,
};
use sisfilt::io::{Output, Role, RunRecord, StepLayout, StepReader, check_files, folder_of};
use sisfilt::lifted::spectral_radius;
use sisfilt::messages::{info, warn};
use sisfilt::model::Model;
use sisfilt::run::{CheckedSpec, RunSpec};
use sisfilt::smoother::{Smoother, human_bytes, memory_bytes};

use super::choice::choice;
use super::in_flag_words;

/// Power-iteration steps of the quick stability warning (`check` takes more).
const POWER_STEPS: usize = 400;
/// Above this many lifted states `estimate` skips its stability check (`check` still does it).
const STABILITY_CHECK_MAX: usize = 100_000;

/// Chains at least this long parse the measurement and input files of a step in parallel
/// (shorter steps cost less than waking a thread).
const PARALLEL_READ_MIN: usize = 512;

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
    /// unknown: lost measurements look like noise (the paper's model); known: lost elements
    /// are empty cells and are skipped.
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
    sisfilt::smoother::parse_bytes(text)
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

/// The measurement file's layout: `t,i,y1..yq`; empty cells only in the known-dropout mode.
fn measurement_layout(q: usize, dropouts: Dropouts) -> StepLayout {
    StepLayout {
        prefix: "y",
        width: q,
        extra: &[],
        allow_empty: dropouts == Dropouts::Known,
        empty_hint: " (a lost measurement? pass --dropouts known to skip empty cells)",
    }
}

/// The truth file's layout: `t,i,x1..xn,gamma`.
fn truth_layout(n: usize) -> StepLayout {
    StepLayout {
        prefix: "x",
        width: n,
        extra: &["gamma"],
        allow_empty: false,
        empty_hint: "",
    }
}

/// The config of an `estimate` run: `--config`, else the `run.json` beside `--meas`. Also
/// returns the folder of that run record, if one was used.
fn estimate_config(args: &EstimateArgs) -> Result<(ConfigSource, Option<PathBuf>)> {
    if let Some(path) = &args.config {
        return Ok((ConfigSource::from_file(path)?, None));
    }
    let missing = || {
        Error::Usage(format!(
            "--config is required: {} has no {} beside it (one written by `sisfilt simulate`)",
            args.meas.display(),
            RunRecord::FILE
        ))
    };
    if args.meas.as_os_str() == "-" {
        return Err(Error::Usage(
            "--config is required when the measurements come from standard input".into(),
        )
        .into());
    }
    let dir = folder_of(&args.meas).to_path_buf();
    let record = RunRecord::load(&dir)?.ok_or_else(missing)?;
    Ok((record.config_source(&dir.join(RunRecord::FILE))?, Some(dir)))
}

fn sha256_hex(text: &str) -> String {
    sha2::Sha256::digest(text.as_bytes())
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect()
}

/// `sisfilt estimate`: the estimates of every `(t, i)`, written as they come (or, with
/// `--smooth`, after the backward pass).
pub fn run(args: &EstimateArgs) -> Result<()> {
    let started = std::time::Instant::now();
    let spec = args.spec()?;
    let (src, run_dir) = estimate_config(args)?;
    let model = Model::from_config(&src)?;
    let d = model.dims;
    let (n, big_n) = (d.n, model.subsystems);

    let inputs_file = args.inputs.clone().or_else(|| {
        run_dir
            .as_ref()
            .map(|dir| dir.join("inputs.csv"))
            .filter(|p| d.m > 0 && p.is_file())
    });
    if d.m == 0
        && let Some(path) = &args.inputs
    {
        return Err(Error::Usage(format!(
            "--inputs {}: the model has no inputs (m = 0), so the file would never be read; leave --inputs out",
            path.display()
        ))
        .into());
    }
    let record = run_dir.as_ref().map(|dir| dir.join(RunRecord::FILE));
    let mut read: Vec<Role> = (args.config.iter().map(|p| Role::new("--config", p)))
        .chain(record.iter().map(|p| Role::new("the run record", p)))
        .collect();
    read.push(Role::new("--meas", &args.meas));
    if let Some(path) = &args.truth {
        read.push(Role::new("--truth", path));
    }
    if let Some(path) = InputStream::path(&model, inputs_file.as_deref()) {
        let what = if args.inputs.is_some() {
            "--inputs"
        } else {
            "the inputs file"
        };
        read.push(Role::new(what, path));
    }
    check_files(&read, &[Role::new("--out", &args.out)])?;
    let inputs = InputStream::open(&model, inputs_file.as_deref())?;
    let meas = open_csv(&args.meas, measurement_layout(d.q, spec.dropouts()), big_n)?;
    let truth = args
        .truth
        .as_ref()
        .map(|p| open_csv(p, truth_layout(n), big_n))
        .transpose()?;
    // Open the output before the long run, so that a bad path fails fast.
    let output = Output::create(&args.out)?;

    warn_about(&spec, &model)?;

    let metadata = metadata(args, &spec, &src, inputs_file.as_deref(), &model);
    let out_name = args.out.display().to_string();
    if spec.output() == EstimateKind::Smoothed {
        let smoother = spec.build_smoother(&model)?;
        let columns = EstimatesColumns {
            n,
            cross: spec.cross_band(&model),
            arrival: spec.update() == Update::Mixture,
        };
        let writer = EstimatesWriter::new(output, args.format(), columns, Some(&metadata))
            .map_err(|e| Error::io(&out_name, e))?;
        return run_smoother(
            args,
            &model,
            smoother,
            &spec,
            FilterIo {
                meas,
                inputs,
                truth,
                writer,
            },
        );
    }
    let filter = spec.build_filter(&model)?;
    let columns = EstimatesColumns {
        n,
        cross: filter.covariance_band(false).map_or(0, |(_, k)| k),
        arrival: filter.arrival().is_some(),
    };
    let writer = EstimatesWriter::new(output, args.format(), columns, Some(&metadata))
        .map_err(|e| Error::io(&out_name, e))?;
    run_filter(
        args,
        &model,
        filter,
        spec.output() == EstimateKind::Predicted,
        FilterIo {
            meas,
            inputs,
            truth,
            writer,
        },
        started,
    )
}

/// The warnings a run of `spec` on `model` deserves before it starts: a distributed filter
/// whose covariance cannot be trusted, an unstable chain.
fn warn_about(spec: &CheckedSpec, model: &Model) -> Result<()> {
    if spec.filter_kind() == FilterKind::Distributed && model.q_is_zero() && model.is_coupled() {
        warn(
            "Q = 0 on a coupled chain: the distributed filter treats the estimated interconnection signals as exact, so its reported covariance P is far too small (docs/theory.md §4); --filter joint keeps it honest (docs/theory.md §8)",
        );
        if spec.output() == EstimateKind::Smoothed {
            warn(
                "Q = 0: the per-subsystem smoother trusts x(t+1) = A x + B v̂ exactly and can be worse than its own filter (docs/theory.md §9); --filter joint --smooth is the remedy",
            );
        }
    }
    if spec.dropouts() == Dropouts::Unknown
        && model.subsystems * model.dims.n <= STABILITY_CHECK_MAX
    {
        let rho = spectral_radius(model, 1, POWER_STEPS)?;
        if rho.value >= 1.0 {
            warn(format!(
                "the spectral radius of A_eff is {:.6} ≥ 1: the unknown-dropout filter diverges on an unstable chain (docs/theory.md §3)",
                rho.value
            ));
        }
    }
    Ok(())
}

/// The metadata at the head of an estimates JSON file.
fn metadata(
    args: &EstimateArgs,
    spec: &CheckedSpec,
    src: &ConfigSource,
    inputs_file: Option<&std::path::Path>,
    model: &Model,
) -> EstimatesMetadata {
    EstimatesMetadata {
        config: ConfigRef {
            path: src.name.clone(),
            sha256: sha256_hex(&src.text),
        },
        inputs: inputs_file.map(|p| p.display().to_string()),
        measurements: args.meas.display().to_string(),
        n: model.dims.n,
        options: spec.recorded(model),
        sisfilt_version: env!("CARGO_PKG_VERSION").to_string(),
        subsystems: model.subsystems,
    }
}

/// The files of a run: measurements, inputs, truth (with `--truth`) and the estimates.
struct FilterIo<R: std::io::Read, T: std::io::Read> {
    meas: StepReader<R>,
    inputs: InputStream,
    truth: Option<StepReader<T>>,
    writer: EstimatesWriter,
}

/// `estimate` without `--smooth`: each step is read, filtered, handed to the writer thread
/// and scored against the truth; `predicted` writes `x̂(t+1|t)`, `T(t+1)` on row `t`.
fn run_filter<R: std::io::Read + Send, T: std::io::Read>(
    args: &EstimateArgs,
    model: &Model,
    mut filter: Box<dyn ChainFilter + '_>,
    predicted: bool,
    io: FilterIo<R, T>,
    started: std::time::Instant,
) -> Result<()> {
    let FilterIo {
        mut meas,
        mut inputs,
        mut truth,
        writer,
    } = io;
    let (n, big_n) = (model.dims.n, model.subsystems);
    let out_name = args.out.display().to_string();
    let mut writer = BackgroundWriter::new(writer, big_n);
    let mut y = vec![0.0; meas.row_values()];
    let mut u = vec![0.0; big_n * model.dims.m];
    let mut x_true = vec![0.0; big_n * (n + 1)];
    let mut scores = Scores::new(n);
    let mut loglik = 0.0;
    // With --predicted, row t is scored against the truth at t + 1.
    let (mut prev_x, mut prev_p) = (vec![0.0; big_n * n], vec![0.0; big_n * n * n]);
    let mut warned_transfer = false;
    let mut steps = 0;
    let mut clock = PhaseClock::default();
    loop {
        // The measurement and input files are parsed side by side, on long chains.
        let next_t = meas.next_t();
        let (t, inputs_read) = clock.read(|| {
            if big_n >= PARALLEL_READ_MIN {
                rayon::join(|| meas.read_step(&mut y), || inputs.next(next_t, &mut u))
            } else {
                (meas.read_step(&mut y), inputs.next(next_t, &mut u))
            }
        });
        let Some(t) = t? else {
            // The inputs were read one step ahead of the measurements' end.
            if let (Ok(()), Some(e)) = (&inputs_read, inputs.read_beyond(steps)) {
                return Err(e.into());
            }
            break;
        };
        inputs_read?;
        clock.filter(|| filter.step(&y, &u))?;
        loglik += filter.log_likelihood().unwrap_or(0.0);
        if !warned_transfer && filter.solver_error_estimate() > TRANSFER_ERROR_WARNING {
            warned_transfer = true;
            warn(format!(
                "the transfer solver's estimated relative error is {:.1e} (> {TRANSFER_ERROR_WARNING:e}) from t = {t} on: its interconnection signals are inaccurate; use --solver banded",
                filter.solver_error_estimate()
            ));
        }
        let (x_hat, p_hat) = if predicted {
            filter.predicted()
        } else {
            filter.filtered()
        };
        check_estimates(t, n, x_hat, p_hat)?;
        let band = filter.covariance_band(predicted).map(|(b, _)| b);
        clock
            .write(|| writer.write_step(t, x_hat, p_hat, band, filter.arrival()))
            .map_err(|e| Error::io(&out_name, e))?;
        if let Some(truth) = truth.as_mut() {
            clock.read(|| read_truth_step(truth, t, &mut x_true))?;
            let scored = match (predicted, t > 1) {
                (false, _) => Some((x_hat, p_hat)),
                (true, true) => Some((prev_x.as_slice(), prev_p.as_slice())),
                (true, false) => None,
            };
            // π(t, i) is scored against γ(t, i), whichever estimate row t holds.
            scores.add(&x_true, scored, filter.arrival());
            if predicted {
                prev_x.copy_from_slice(x_hat);
                prev_p.copy_from_slice(p_hat);
            }
        }
        steps = t;
    }
    finish_inputs(meas.name(), steps, inputs)?;
    let elapsed = started.elapsed().as_secs_f64();
    info(format!(
        "estimate: {steps} steps × {big_n} subsystems in {elapsed:.3} s ({:.3e} subsystem-steps/s)",
        (steps * big_n) as f64 / elapsed.max(1e-9)
    ));
    let summary = EstimatesSummary {
        loglik: filter.log_likelihood().map(|_| loglik),
        ..scores.summary(truth.is_some(), filter.arrival().is_some())?
    };
    if let Some(loglik) = summary.loglik {
        info(format!(
            "log-likelihood of the measurements: {loglik:.6e} over {steps} steps"
        ));
    }
    report_summary(&summary);
    let busy = clock.write(|| -> Result<f64> {
        let (writer, busy) = writer.finish().map_err(|e| Error::io(&out_name, e))?;
        writer.commit(&summary)?;
        Ok(busy)
    })?;
    if args.timings {
        let rows = steps * big_n;
        eprintln!(
            "timings: {}; the writer thread was busy {:.3} s",
            clock.summary(started.elapsed(), rows),
            busy
        );
    }
    Ok(())
}

/// `estimate --smooth`: the forward pass over the whole file (refused politely once its
/// stored steps exceed `--max-memory`), the backward pass, then every row.
fn run_smoother<R: std::io::Read, T: std::io::Read>(
    args: &EstimateArgs,
    model: &Model,
    mut smoother: Box<dyn Smoother + '_>,
    spec: &CheckedSpec,
    io: FilterIo<R, T>,
) -> Result<()> {
    let FilterIo {
        mut meas,
        mut inputs,
        mut truth,
        mut writer,
    } = io;
    let (n, big_n) = (model.dims.n, model.subsystems);
    let kind = spec.smoother_kind();
    let limit = spec.max_memory();
    let mut y = vec![0.0; meas.row_values()];
    let mut u = vec![0.0; big_n * model.dims.m];
    let mut truth_rows: Vec<Vec<f64>> = Vec::new();
    // The forward pass's π of every step (the mixture update): the smoother keeps them.
    let mut arrival: Vec<Vec<f64>> = Vec::new();
    let mut steps = 0;
    while let Some(t) = meas.read_step(&mut y)? {
        let need = memory_bytes(model, kind, t);
        if need > limit {
            return Err(Error::Usage(format!(
                "--smooth: the stored forward pass needs {} by t = {t} ({need} bytes), above --max-memory {} ({limit} bytes); raise --max-memory, or smooth a shorter file",
                human_bytes(need),
                human_bytes(limit)
            ))
            .into());
        }
        inputs.next(t, &mut u)?;
        smoother.step(&y, &u)?;
        if let Some(pi) = smoother.arrival() {
            arrival.push(pi.to_vec());
        }
        if let Some(truth) = truth.as_mut() {
            let mut row = vec![0.0; big_n * (n + 1)];
            read_truth_step(truth, t, &mut row)?;
            truth_rows.push(row);
        }
        steps = t;
    }
    finish_inputs(meas.name(), steps, inputs)?;
    let smoothed = smoother.finish()?;
    for note in &smoothed.notes {
        warn(note);
    }
    let out_name = args.out.display().to_string();
    let mut scores = Scores::new(n);
    for (idx, (x, p)) in smoothed.x.iter().zip(&smoothed.p).enumerate() {
        check_estimates(idx + 1, n, x, p)?;
        let band = smoothed.bands.as_ref().map(|b| &b[idx]);
        let pi = arrival.get(idx).map(Vec::as_slice);
        writer
            .write_step(idx + 1, x, p, band, pi)
            .map_err(|e| Error::io(&out_name, e))?;
        if let Some(row) = truth_rows.get(idx) {
            scores.add(row, Some((x, p)), pi);
        }
    }
    let summary = scores.summary(truth.is_some(), !arrival.is_empty())?;
    report_summary(&summary);
    Ok(writer.commit(&summary)?)
}

/// The figures of a run scored against `--truth`: the accuracy of the estimates
/// (docs/theory.md §11) and how well `π` detects the lost measurements (§10).
struct Scores {
    n: usize,
    accuracy: Accuracy,
    detection: Detection,
}

impl Scores {
    fn new(n: usize) -> Self {
        Self {
            n,
            accuracy: Accuracy::new(n),
            detection: Detection::default(),
        }
    }

    /// Scores one step against its truth (`N (n + 1)` values: each subsystem's states, then
    /// `γ`): the estimates `(x̂, P)` (`N·n` and `N·n²`), when given, and `π`, when given.
    fn add(&mut self, truth: &[f64], estimates: Option<(&[f64], &[f64])>, arrival: Option<&[f64]>) {
        let n = self.n;
        for (i, row) in truth.chunks_exact(n + 1).enumerate() {
            if let Some((x, p)) = estimates {
                self.accuracy.add(
                    &row[..n],
                    &x[i * n..(i + 1) * n],
                    &p[i * n * n..(i + 1) * n * n],
                );
            }
            if let Some(pi) = arrival {
                self.detection.add(pi[i], row[n]);
            }
        }
    }

    /// The summary of a run: the accuracy with `--truth`, the detection with `--truth` and
    /// `π`. Not one scored term is an error, since figures over nothing would read as a
    /// perfect score.
    fn summary(&self, truth: bool, arrival: bool) -> Result<EstimatesSummary> {
        if !truth {
            return Ok(EstimatesSummary::default());
        }
        let accuracy = self.accuracy.report();
        if accuracy.terms == 0 {
            return Err(Error::Usage(
                "--truth: no step could be scored (with --predicted, row t is scored against the truth at t + 1, and the measurements hold one step)".into(),
            )
            .into());
        }
        Ok(EstimatesSummary {
            accuracy: Some(accuracy),
            detection: arrival.then(|| self.detection.report()),
            loglik: None,
        })
    }
}

/// Reads the truth of step `t` into `out`; a truth file that ends before the measurements is
/// bad input.
fn read_truth_step<R: std::io::Read>(
    truth: &mut StepReader<R>,
    t: usize,
    out: &mut [f64],
) -> Result<()> {
    if truth.read_step(out)?.is_none() {
        return Err(Error::File {
            file: truth.name().to_string(),
            msg: format!(
                "ends before t = {t}; the truth must cover every step of the measurements"
            ),
        }
        .into());
    }
    Ok(())
}

/// Ends a run over `steps` measured steps: an empty measurement file is bad input, and an
/// inputs file must end where the measurements do.
fn finish_inputs(meas_name: &str, steps: usize, inputs: InputStream) -> Result<()> {
    if steps == 0 {
        return Err(Error::File {
            file: meas_name.to_string(),
            msg: "holds no measurement rows".into(),
        }
        .into());
    }
    inputs.finish(steps)?;
    Ok(())
}

/// Wall-clock time spent in each phase of `estimate` (`--timings`).
#[derive(Default)]
struct PhaseClock {
    read: std::time::Duration,
    filter: std::time::Duration,
    write: std::time::Duration,
}

impl PhaseClock {
    fn time<R>(slot: &mut std::time::Duration, f: impl FnOnce() -> R) -> R {
        let start = std::time::Instant::now();
        let r = f();
        *slot += start.elapsed();
        r
    }

    fn read<R>(&mut self, f: impl FnOnce() -> R) -> R {
        Self::time(&mut self.read, f)
    }

    fn filter<R>(&mut self, f: impl FnOnce() -> R) -> R {
        Self::time(&mut self.filter, f)
    }

    fn write<R>(&mut self, f: impl FnOnce() -> R) -> R {
        Self::time(&mut self.write, f)
    }

    /// `read R s, filter F s, write W s, other O s, total X s, K rows, Y rows/s`.
    fn summary(&self, total: std::time::Duration, rows: usize) -> String {
        let secs = |d: std::time::Duration| d.as_secs_f64();
        let other = secs(total) - secs(self.read) - secs(self.filter) - secs(self.write);
        format!(
            "read {:.3} s, filter {:.3} s, write {:.3} s, other {:.3} s, total {:.3} s, {rows} rows, {:.0} rows/s",
            secs(self.read),
            secs(self.filter),
            secs(self.write),
            other.max(0.0),
            secs(total),
            rows as f64 / secs(total).max(1e-9)
        )
    }
}

/// Prints the figures of a run scored against the truth on standard error: the accuracy,
/// with the NEES warning of docs/theory.md §11, and the detection of lost measurements.
fn report_summary(summary: &EstimatesSummary) {
    if let Some(r) = &summary.accuracy {
        report_accuracy(r);
    }
    if let Some(d) = &summary.detection {
        sisfilt::messages::report("detection", d.summary());
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

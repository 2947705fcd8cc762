//! The commands behind the command line: each reads its inputs, runs the library and writes
//! its outputs. Warnings go to standard error through [`warn`] (see [`crate::messages`]); data to
//! standard output or files.

use std::io::Write;
use std::path::{Path, PathBuf};

use anyhow::{Context, Result};

use sha2::Digest;

use crate::accuracy::{Accuracy, AccuracyReport};
use crate::cli::FilterKind;
use crate::cli::{Command, EstimateArgs, EvaluateArgs, PlotCommand, SimulateArgs};
use crate::config::ConfigSource;
use crate::error::Error;
use crate::filter::joint::{DEFAULT_BAND, DEFAULT_BAND_TOL, flops_per_subsystem_step};
use crate::filter::{
    CentralizedFilter, ChainFilter, Dropouts, JointFilter, JointOptions, SecondMoment,
    TwoStepOptions, check_estimates, two_step,
};
use crate::inputs::{InputStream, open_csv};
use crate::interconnect::{ChainSolver, TRANSFER_ERROR_WARNING};
use crate::io::estimates::{BackgroundWriter, EstimatesWriter, Format};
use crate::io::{CsvWriter, Output, Role, RunRecord, StepLayout, check_files, folder_of};
use crate::lifted::{a_eff_band, spectral_radius};
use crate::messages::{Verbosity, info, verbosity};
use crate::model::{MATRIX_KEYS, Model};
use crate::simulate::simulate;
use crate::smoother::{
    CentralizedSmoother, DEFAULT_MAX_MEMORY, DistributedSmoother, JointSmoother, Smoother,
    SmootherKind, human_bytes, memory_bytes,
};

/// Power-iteration steps for the spectral radius: `check` takes its time, `estimate` only
/// wants a quick stability warning.
const CHECK_POWER_STEPS: usize = 4000;
const ESTIMATE_POWER_STEPS: usize = 400;
/// Above this many lifted states `estimate` skips its stability check (`check` still does it).
const ESTIMATE_STABILITY_CHECK_MAX: usize = 100_000;

/// Chains at least this long parse the measurement and input files of a step in parallel
/// (shorter steps cost less than waking a thread).
const PARALLEL_READ_MIN: usize = 512;

pub use crate::messages::warn;

/// Writes `text` and a line break to standard output; a closed pipe comes back as an
/// [`Error::Io`] of kind `BrokenPipe`, which the binary ends quietly with exit 0
/// (`println!` would panic instead).
fn print_stdout(text: &str) -> Result<()> {
    let mut out = Output::create(Path::new("-"))?;
    writeln!(out, "{text}").map_err(|e| Error::io("<stdout>", e))?;
    out.commit()?;
    Ok(())
}

/// Runs one command.
pub fn run(command: Command) -> Result<()> {
    match command {
        Command::Check { config } => check(&config),
        Command::Simulate(args) => simulate_command(&args),
        // On a worker of rayon's pool, so that the parallel loops of every step (filter,
        // writer, readers) start without waking the pool from outside each time.
        Command::Estimate(args) => rayon::scope(|_| estimate(&args)),
        Command::Evaluate(args) => evaluate_command(&args),
        Command::Plot(PlotCommand::Series(args)) => crate::plot::series::run(&args),
        Command::Plot(PlotCommand::Heatmap(args)) => crate::plot::heatmap::run(&args),
        Command::Plot(PlotCommand::Evaluate(args)) => crate::plot::evaluate::run(&args),
        Command::Completions { shell } => completions(shell),
        Command::Man { command } => man_page(&command),
    }
}

/// Writes `text` to standard output (quietly stopping on a closed pipe, like every output).
fn print_to_stdout(text: &[u8]) -> Result<()> {
    let mut out = Output::create(Path::new("-"))?;
    std::io::Write::write_all(&mut out, text).map_err(|e| Error::io("<stdout>", e))?;
    out.commit()?;
    Ok(())
}

/// `sisfilt completions SHELL`: the completion script, generated from the clap definition.
fn completions(shell: clap_complete::Shell) -> Result<()> {
    let mut cmd = <crate::cli::Cli as clap::CommandFactory>::command();
    let mut script = Vec::new();
    clap_complete::generate(shell, &mut cmd, "sisfilt", &mut script);
    print_to_stdout(&script)
}

/// `sisfilt man [COMMAND…]`: the man page (roff) of `sisfilt` or of one of its commands
/// (`sisfilt man plot series` is the page `sisfilt-plot-series(1)`).
fn man_page(path: &[String]) -> Result<()> {
    let mut cmd = <crate::cli::Cli as clap::CommandFactory>::command();
    // Building propagates the global options (--quiet, --verbose) into every command.
    cmd.build();
    let mut name = "sisfilt".to_string();
    for word in path {
        let Some(sub) = cmd.find_subcommand(word).cloned() else {
            let known: Vec<&str> = cmd
                .get_subcommands()
                .map(clap::Command::get_name)
                .filter(|n| *n != "help")
                .collect();
            return Err(Error::Usage(format!(
                "man: `{name}` has no command `{word}`; expected one of: {}",
                known.join(", ")
            ))
            .into());
        };
        name = format!("{name}-{word}");
        cmd = sub;
    }
    let cmd = cmd.name(name).version(env!("CARGO_PKG_VERSION"));
    let mut page = Vec::new();
    clap_mangen::Man::new(cmd)
        .render(&mut page)
        .context("rendering the man page")?;
    print_to_stdout(&page)
}

fn check(path: &Path) -> Result<()> {
    let model = Model::load(path)?;
    let d = model.dims;
    // Everything simulate reads: the inputs file too.
    let mut inputs = InputStream::open(&model, None)?;
    let mut u = vec![0.0; model.subsystems * d.m];
    for t in 1..=model.steps {
        inputs.next(t, &mut u)?;
    }
    inputs.finish(model.steps)?;

    let mut report: Vec<String> = Vec::new();
    let mut warnings: Vec<String> = Vec::new();
    report.push(format!("config: {}", path.display()));
    report.push(format!(
        "chain: N = {} subsystems, T = {} steps",
        model.subsystems, model.steps
    ));
    report.push(format!(
        "dimensions: n = {}, m = {}, q = {}, plus = {}, minus = {}",
        d.n, d.m, d.q, d.plus, d.minus
    ));
    let mut varying = Vec::new();
    for key in MATRIX_KEYS.iter().copied().chain(["p"]) {
        let (time, space) = model.variation(key);
        let how = match (time, space) {
            (true, true) => "time and space",
            (true, false) => "time",
            (false, true) => "space",
            (false, false) => continue,
        };
        varying.push(format!("{key} ({how})"));
    }
    report.push(format!(
        "varying parameters: {}",
        if varying.is_empty() {
            "none".to_string()
        } else {
            varying.join(", ")
        }
    ));
    report.push(format!(
        "process noise: {}",
        if model.q_is_zero() {
            "Q = 0 (the paper's setting)"
        } else {
            "Q > 0"
        }
    ));
    let windows = model.windows();
    for (k, w) in windows.iter().enumerate() {
        if w.first > model.steps {
            break;
        }
        let last = windows
            .get(k + 1)
            .map_or(model.steps, |n| (n.first - 1).min(model.steps));
        let solver = ChainSolver::new(&model, w.first)?;
        let rho = spectral_radius(&model, w.first, CHECK_POWER_STEPS)?;
        let b = a_eff_band(&model, w.first, &solver, DEFAULT_BAND_TOL).half_width();
        let k = DEFAULT_BAND.min(model.subsystems - 1);
        let joint_line = format!(
            "t = {}..{}: A_eff band half-width b = {b} (tol {DEFAULT_BAND_TOL:e}); joint filter (--band {k}): about {:.1} kflop per subsystem-step",
            w.first,
            last,
            flops_per_subsystem_step(d.n, k, b, model.subsystems, true) / 1e3,
        );
        report.push(format!(
            "t = {}..{}: interconnection condition estimate {:.3e} (1-norm), spectral radius of A_eff {:.6} ({})",
            w.first,
            last,
            solver.condition(),
            rho.value,
            if rho.exact {
                "exact"
            } else {
                "power-iteration estimate"
            }
        ));
        report.push(joint_line);
        if rho.value >= 1.0 {
            warnings.push(format!(
                "t = {}..{last}: the spectral radius of A_eff is {:.6} ≥ 1: the chain is not stable, and the unknown-dropout filter diverges (docs/theory.md §3)",
                w.first, rho.value
            ));
        }
    }
    let k = DEFAULT_BAND.min(model.subsystems - 1);
    report.push(format!(
        "smoothing memory for T = {}: distributed {}, joint (--band {k}) {}, centralized {} (--max-memory, default {})",
        model.steps,
        human_bytes(memory_bytes(&model, SmootherKind::Distributed, model.steps)),
        human_bytes(memory_bytes(&model, SmootherKind::Joint(k), model.steps)),
        human_bytes(memory_bytes(&model, SmootherKind::Centralized, model.steps)),
        human_bytes(DEFAULT_MAX_MEMORY),
    ));
    // Print only once everything passed, so that a bad config prints nothing on stdout.
    print_stdout(&report.join("\n"))?;
    for w in warnings {
        warn(w);
    }
    Ok(())
}

fn simulate_command(args: &SimulateArgs) -> Result<()> {
    // The source too: run.json records the config's text.
    let src = ConfigSource::from_file(&args.config)?;
    let model = Model::from_config(&src)?;
    // Fail on an ill-posed chain or unusable inputs before creating anything.
    for w in model.windows().iter().filter(|w| w.first <= model.steps) {
        ChainSolver::new(&model, w.first)?;
    }
    let out_dir = &args.out;
    let read = config_files(&args.config, &model);
    let written: Vec<PathBuf> = simulation_files(model.dims.m)
        .map(|name| out_dir.join(name))
        .collect();
    let written: Vec<Role> = written.iter().map(|p| Role::new("--out", p)).collect();
    check_files(&read, &written)?;
    let inputs = InputStream::open(&model, None)?;
    if out_dir.exists() && !out_dir.is_dir() {
        return Err(Error::Usage(format!(
            "--out {}: exists and is not a folder",
            out_dir.display()
        ))
        .into());
    }
    // The folders this run creates, innermost first: a failed run removes them again.
    let created: Vec<PathBuf> = out_dir
        .ancestors()
        .take_while(|a| !a.as_os_str().is_empty() && !a.exists())
        .map(Path::to_path_buf)
        .collect();
    std::fs::create_dir_all(out_dir).map_err(|e| {
        Error::Usage(format!(
            "--out {}: cannot create the folder: {e}",
            out_dir.display()
        ))
    })?;
    let result = write_simulation(args, &src, &model, inputs);
    if result.is_err() {
        for dir in &created {
            // Fails, and so keeps the folder, if anything else appeared in it meanwhile.
            if std::fs::remove_dir(dir).is_err() {
                break;
            }
        }
    }
    result
}

/// The files a run of `model` reads: its config, and the inputs file the config names.
fn config_files<'a>(config: &'a Path, model: &'a Model) -> Vec<Role<'a>> {
    let mut read = vec![Role::new("the config", config)];
    if let Some(path) = InputStream::path(model, None) {
        read.push(Role::new("the inputs file", path));
    }
    read
}

/// The files `simulate` writes into its folder, for a model with `m` inputs.
fn simulation_files(m: usize) -> impl Iterator<Item = &'static str> {
    ["truth.csv", "measurements.csv"]
        .into_iter()
        .chain((m > 0).then_some("inputs.csv"))
        .chain([RunRecord::FILE])
}

/// Simulates and writes the files of `simulate` into the existing folder `args.out`; each file
/// appears (atomically) only once every file is complete.
fn write_simulation(
    args: &SimulateArgs,
    src: &ConfigSource,
    model: &Model,
    mut inputs: InputStream,
) -> Result<()> {
    let out_dir = &args.out;
    let seed = args.seed.unwrap_or(model.seed);
    let d = model.dims;
    let file = |name: &str| -> Result<Output> { Ok(Output::create(&out_dir.join(name))?) };
    let header = |prefix: &str, width: usize, extra: &[&str]| -> Vec<String> {
        let mut h = vec!["t".to_string(), "i".to_string()];
        h.extend((1..=width).map(|k| format!("{prefix}{k}")));
        h.extend(extra.iter().map(|s| s.to_string()));
        h
    };
    let io_err = |name: &'static str| move |e| Error::io(name, e);
    let mut truth = CsvWriter::new(file("truth.csv")?, &header("x", d.n, &["gamma"]))
        .map_err(io_err("truth.csv"))?;
    let mut meas = CsvWriter::new(file("measurements.csv")?, &header("y", d.q, &[]))
        .map_err(io_err("measurements.csv"))?;
    let mut inputs_out = if d.m > 0 {
        Some(
            CsvWriter::new(file("inputs.csv")?, &header("u", d.m, &[]))
                .map_err(io_err("inputs.csv"))?,
        )
    } else {
        None
    };
    let mut record_out = file(RunRecord::FILE)?;

    let mut y_row = vec![0.0; d.q];
    simulate(model, model.steps, seed, &mut inputs, |step| {
        for i in 0..model.subsystems {
            let gamma = step.gamma[i];
            truth
                .row(
                    step.t,
                    i + 1,
                    &step.x[i * d.n..(i + 1) * d.n],
                    Some(gamma as u8),
                )
                .map_err(|e| Error::io("truth.csv", e))?;
            y_row.copy_from_slice(&step.y[i * d.q..(i + 1) * d.q]);
            if args.mark_missing && !gamma {
                y_row.fill(f64::NAN);
            }
            meas.row(step.t, i + 1, &y_row, None)
                .map_err(|e| Error::io("measurements.csv", e))?;
            if let Some(w) = inputs_out.as_mut() {
                w.row(step.t, i + 1, &step.u[i * d.m..(i + 1) * d.m], None)
                    .map_err(|e| Error::io("inputs.csv", e))?;
            }
        }
        Ok(())
    })?;
    inputs.finish(model.steps)?;

    let mut files = vec!["truth.csv".to_string(), "measurements.csv".to_string()];
    if d.m > 0 {
        files.push("inputs.csv".into());
    }
    let config_dir = RunRecord::relative_dir(out_dir, &src.dir);
    let record = RunRecord {
        sisfilt_version: env!("CARGO_PKG_VERSION").to_string(),
        seed,
        subsystems: model.subsystems,
        steps: model.steps,
        mark_missing: args.mark_missing,
        config_path: args.config.display().to_string(),
        config_dir,
        config_toml: src.text.clone(),
        config: src.raw.clone(),
        files,
    };
    serde_json::to_writer_pretty(&mut record_out, &record).context("writing run.json")?;
    std::io::Write::write_all(&mut record_out, b"\n").map_err(|e| Error::io("run.json", e))?;

    truth
        .into_inner()
        .map_err(|e| Error::io("truth.csv", e))?
        .commit()?;
    meas.into_inner()
        .map_err(|e| Error::io("measurements.csv", e))?
        .commit()?;
    if let Some(w) = inputs_out {
        w.into_inner()
            .map_err(|e| Error::io("inputs.csv", e))?
            .commit()?;
    }
    record_out.commit()?;
    info(format!(
        "simulate: T = {} steps × N = {} subsystems (seed {seed}) into {}",
        model.steps,
        model.subsystems,
        out_dir.display()
    ));
    Ok(())
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

fn estimate(args: &EstimateArgs) -> Result<()> {
    let started = std::time::Instant::now();
    let (src, run_dir) = estimate_config(args)?;
    let model = Model::from_config(&src)?;
    let d = model.dims;
    let (n, big_n) = (d.n, model.subsystems);

    let mut opts = if args.paper {
        TwoStepOptions::paper()
    } else {
        TwoStepOptions::default()
    };
    opts.solver = args.solver.unwrap_or(opts.solver);
    opts.second_moment = args.second_moment.unwrap_or(opts.second_moment);
    opts.interconnect_from = args.interconnect_from.unwrap_or(opts.interconnect_from);
    opts.dropouts = args.dropouts;
    let joint = joint_options(args)?;
    if args.max_memory.is_some() && !args.smooth {
        return Err(Error::Usage("--max-memory belongs to --smooth".into()).into());
    }

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
    let mut inputs = InputStream::open(&model, inputs_file.as_deref())?;
    let mut meas = open_csv(&args.meas, measurement_layout(d.q, opts.dropouts), big_n)?;
    let mut truth = args
        .truth
        .as_ref()
        .map(|p| open_csv(p, truth_layout(n), big_n))
        .transpose()?;
    let format = args.format.unwrap_or(
        if args
            .out
            .extension()
            .is_some_and(|e| e.eq_ignore_ascii_case("json"))
        {
            Format::Json
        } else {
            Format::Csv
        },
    );
    // Open the output before the long run, so that a bad path fails fast.
    let output = Output::create(&args.out)?;

    if args.filter == FilterKind::Distributed && model.q_is_zero() && model.is_coupled() {
        warn(
            "Q = 0 on a coupled chain: the distributed filter treats the estimated interconnection signals as exact, so its reported covariance P is far too small (docs/theory.md §4); --filter joint keeps it honest (docs/theory.md §8)",
        );
        if args.smooth {
            warn(
                "Q = 0: the per-subsystem smoother trusts x(t+1) = A x + B v̂ exactly and can be worse than its own filter (docs/theory.md §9); --filter joint --smooth is the remedy",
            );
        }
    }
    if opts.dropouts == Dropouts::Unknown && big_n * n <= ESTIMATE_STABILITY_CHECK_MAX {
        let rho = spectral_radius(&model, 1, ESTIMATE_POWER_STEPS)?;
        if rho.value >= 1.0 {
            warn(format!(
                "the spectral radius of A_eff is {:.6} ≥ 1: the unknown-dropout filter diverges on an unstable chain (docs/theory.md §3)",
                rho.value
            ));
        }
    }

    let two_step_only = args.filter == FilterKind::Distributed;
    let metadata = serde_json::json!({
        "sisfilt_version": env!("CARGO_PKG_VERSION"),
        "config": { "path": src.name, "sha256": sha256_hex(&src.text) },
        "measurements": args.meas.display().to_string(),
        "inputs": inputs_file.as_ref().map(|p| p.display().to_string()),
        "options": {
            "filter": args.filter,
            // The two-step filter's options; the other filters ignore them (null).
            "solver": two_step_only.then_some(opts.solver),
            "second_moment": two_step_only.then_some(opts.second_moment),
            "interconnect_from": two_step_only.then_some(opts.interconnect_from),
            "dropouts": opts.dropouts,
            "paper": args.paper,
            "output": if args.smooth { "smoothed" } else if args.predicted { "predicted" } else { "filtered" },
            "joint": joint.map(|j| serde_json::json!({
                "band": j.band.min(big_n - 1),
                "band_tol": j.band_tol,
                "loading": j.loading_for(&model),
                "second_moment": j.second_moment,
            })),
        },
        "subsystems": big_n,
        "n": n,
    });
    let out_name = args.out.display().to_string();
    if args.smooth {
        let smoother = make_smoother(args, &model, opts, joint)?;
        let k = joint.map_or(0, |j| j.band.min(big_n - 1));
        let writer = EstimatesWriter::new(output, format, n, k, metadata)
            .map_err(|e| Error::io(&out_name, e))?;
        return run_smoother(
            args,
            &model,
            smoother,
            SmootherIo {
                meas,
                inputs,
                truth,
                writer,
            },
        );
    }
    let mut filter: Box<dyn ChainFilter> = match (args.filter, joint) {
        (FilterKind::Joint, Some(j)) => Box::new(JointFilter::new(&model, j)?),
        (FilterKind::Centralized, _) => Box::new(CentralizedFilter::new(
            &model,
            opts.dropouts == Dropouts::Known,
            args.max_lifted,
        )?),
        _ => two_step(&model, opts)?,
    };
    let cross = filter.covariance_band(false).map_or(0, |(_, k)| k);
    let writer = EstimatesWriter::new(output, format, n, cross, metadata)
        .map_err(|e| Error::io(&out_name, e))?;
    let mut writer = BackgroundWriter::new(
        writer,
        big_n,
        big_n * n,
        big_n * n * n,
        (cross > 0).then_some((big_n, n, cross)),
    );
    let mut y = vec![0.0; meas.row_values()];
    let mut u = vec![0.0; big_n * d.m];
    let mut x_true = vec![0.0; big_n * (n + 1)];
    let mut accuracy = Accuracy::new(n);
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
        if !warned_transfer && filter.solver_error_estimate() > TRANSFER_ERROR_WARNING {
            warned_transfer = true;
            warn(format!(
                "the transfer solver's estimated relative error is {:.1e} (> {TRANSFER_ERROR_WARNING:e}) from t = {t} on: its interconnection signals are inaccurate; use --solver banded",
                filter.solver_error_estimate()
            ));
        }
        let (x_hat, p_hat) = if args.predicted {
            filter.predicted()
        } else {
            filter.filtered()
        };
        check_estimates(t, n, x_hat, p_hat)?;
        let band = filter.covariance_band(args.predicted).map(|(b, _)| b);
        clock
            .write(|| writer.write_step(t, x_hat, p_hat, band))
            .map_err(|e| Error::io(&out_name, e))?;
        if let Some(truth) = truth.as_mut() {
            clock.read(|| read_truth_step(truth, t, &mut x_true))?;
            let scored = match (args.predicted, t > 1) {
                (false, _) => Some((x_hat, p_hat)),
                (true, true) => Some((prev_x.as_slice(), prev_p.as_slice())),
                (true, false) => None,
            };
            if let Some((xs, ps)) = scored {
                for i in 0..big_n {
                    accuracy.add(
                        &x_true[i * (n + 1)..i * (n + 1) + n],
                        &xs[i * n..(i + 1) * n],
                        &ps[i * n * n..(i + 1) * n * n],
                    );
                }
            }
            if args.predicted {
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
    let report = truth.is_some().then(|| scored(&accuracy)).transpose()?;
    if let Some(r) = &report {
        report_accuracy(r);
    }
    let busy = clock.write(|| -> Result<f64> {
        let (writer, busy) = writer.finish().map_err(|e| Error::io(&out_name, e))?;
        writer.commit(report.as_ref())?;
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

/// The smoother of `--filter` (docs/theory.md §9).
fn make_smoother<'m>(
    args: &EstimateArgs,
    model: &'m Model,
    opts: TwoStepOptions,
    joint: Option<JointOptions>,
) -> Result<Box<dyn Smoother + 'm>> {
    Ok(match (args.filter, joint) {
        (FilterKind::Joint, Some(j)) => Box::new(JointSmoother::new(model, j)?),
        (FilterKind::Centralized, _) => Box::new(CentralizedSmoother::new(
            model,
            opts.dropouts == Dropouts::Known,
            args.max_lifted,
        )?),
        _ => Box::new(DistributedSmoother::new(model, two_step(model, opts)?)),
    })
}

/// The files of a smoothing run.
struct SmootherIo<R: std::io::Read, T: std::io::Read> {
    meas: crate::io::StepReader<R>,
    inputs: InputStream,
    truth: Option<crate::io::StepReader<T>>,
    writer: EstimatesWriter,
}

/// `estimate --smooth`: the forward pass over the whole file (refused politely once its
/// stored steps exceed `--max-memory`), the backward pass, then every row.
fn run_smoother<R: std::io::Read, T: std::io::Read>(
    args: &EstimateArgs,
    model: &Model,
    mut smoother: Box<dyn Smoother + '_>,
    io: SmootherIo<R, T>,
) -> Result<()> {
    let SmootherIo {
        mut meas,
        mut inputs,
        mut truth,
        mut writer,
    } = io;
    let (n, big_n) = (model.dims.n, model.subsystems);
    let kind = match args.filter {
        FilterKind::Distributed => SmootherKind::Distributed,
        FilterKind::Centralized => SmootherKind::Centralized,
        FilterKind::Joint => SmootherKind::Joint(args.band.unwrap_or(DEFAULT_BAND)),
    };
    let limit = args.max_memory.unwrap_or(DEFAULT_MAX_MEMORY);
    let mut y = vec![0.0; meas.row_values()];
    let mut u = vec![0.0; big_n * model.dims.m];
    let mut truth_rows: Vec<Vec<f64>> = Vec::new();
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
    let mut accuracy = Accuracy::new(n);
    for (idx, (x, p)) in smoothed.x.iter().zip(&smoothed.p).enumerate() {
        check_estimates(idx + 1, n, x, p)?;
        let band = smoothed.bands.as_ref().map(|b| &b[idx]);
        writer
            .write_step(idx + 1, x, p, band)
            .map_err(|e| Error::io(&out_name, e))?;
        for i in 0..big_n {
            if let Some(row) = truth_rows.get(idx) {
                accuracy.add(
                    &row[i * (n + 1)..i * (n + 1) + n],
                    &x[i * n..(i + 1) * n],
                    &p[i * n * n..(i + 1) * n * n],
                );
            }
        }
    }
    let report = truth.is_some().then(|| scored(&accuracy)).transpose()?;
    if let Some(r) = &report {
        report_accuracy(r);
    }
    Ok(writer.commit(report.as_ref())?)
}

/// The accuracy figures of a run scored against `--truth`; an error when not one term was
/// scored, since figures over nothing would read as a perfect score.
fn scored(accuracy: &Accuracy) -> Result<AccuracyReport> {
    let report = accuracy.report();
    if report.terms == 0 {
        return Err(Error::Usage(
            "--truth: no step could be scored (with --predicted, row t is scored against the truth at t + 1, and the measurements hold one step)".into(),
        )
        .into());
    }
    Ok(report)
}

/// Reads the truth of step `t` into `out`; a truth file that ends before the measurements is
/// bad input.
fn read_truth_step<R: std::io::Read>(
    truth: &mut crate::io::StepReader<R>,
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

/// The joint filter's options from the command line (`None` for the other filters, which
/// reject the joint filter's options: docs/theory.md §13).
fn joint_options(args: &EstimateArgs) -> Result<Option<JointOptions>> {
    if args.filter != FilterKind::Joint {
        let only_joint = [
            (args.band.is_some(), "--band"),
            (args.band_tol.is_some(), "--band-tol"),
            (args.loading.is_some(), "--loading"),
            (
                args.second_moment == Some(SecondMoment::Band),
                "--second-moment band",
            ),
        ];
        if let Some((_, name)) = only_joint.iter().find(|(given, _)| *given) {
            return Err(Error::Usage(format!(
                "{name} belongs to the joint filter; add --filter joint"
            ))
            .into());
        }
        return Ok(None);
    }
    let second_moment = match args.second_moment {
        Some(SecondMoment::Paper) => {
            return Err(Error::Usage(
                "--second-moment paper belongs to the distributed filter; the joint filter takes band, lifted or local".into(),
            )
            .into());
        }
        Some(s) => s,
        None => SecondMoment::Band,
    };
    let defaults = JointOptions::default();
    Ok(Some(JointOptions {
        band: args.band.unwrap_or(defaults.band),
        band_tol: args.band_tol.unwrap_or(defaults.band_tol),
        loading: args.loading,
        second_moment,
        dropouts: args.dropouts,
    }))
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

/// Prints accuracy figures on standard error, with the NEES warning of docs/theory.md §11.
fn report_accuracy(r: &AccuracyReport) {
    crate::messages::report("accuracy", r.summary());
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

fn evaluate_command(args: &EvaluateArgs) -> Result<()> {
    use std::io::IsTerminal;
    let model = Model::load(&args.config)?;
    if let Some(out) = &args.out {
        check_files(
            &config_files(&args.config, &model),
            &[Role::new("--out", out)],
        )?;
    }
    let out = args.out.as_ref().map(|p| Output::create(p)).transpose()?;
    let opts = crate::evaluate::EvaluateOptions {
        runs: args.runs,
        seed: args.seed.unwrap_or(model.seed),
        burn_in: args.burn_in,
        max_lifted: args.max_lifted,
        band: args.band,
        filters: args.filters.clone(),
        smooth: args.smooth,
    };
    let config_name = args.config.display().to_string();
    let sweep = args.sweep_p.as_deref();
    let total_runs = args.runs * sweep.map_or(1, <[f64]>::len);
    let bar = if std::io::stderr().is_terminal() && verbosity() >= Verbosity::Normal {
        indicatif::ProgressBar::new(total_runs as u64)
    } else {
        indicatif::ProgressBar::hidden()
    };
    info(format!(
        "evaluate: {total_runs} runs of T = {} × N = {} on {} threads",
        model.steps,
        model.subsystems,
        rayon::current_num_threads()
    ));
    if let Some(values) = sweep {
        let result = crate::evaluate::sweep_p(&model, &config_name, opts, values, || bar.inc(1))?;
        bar.finish_and_clear();
        info(format!("evaluate: {:.2} s", result.total_wall_time_s));
        for (p, e) in result.sweep_p.iter().zip(&result.evaluations) {
            warn_left_out(e, &format!(" at p = {p}"));
        }
        write_json(out, &result)?;
        return print_stdout(result.table().trim_end_matches('\n'));
    }
    let result = crate::evaluate::evaluate(&model, &config_name, opts, || bar.inc(1))?;
    bar.finish_and_clear();
    info(format!(
        "evaluate: {:.2} s ({})",
        result.total_wall_time_s,
        result
            .filters
            .iter()
            .map(|f| format!("{} {:.2} s", f.name, f.wall_time_s))
            .collect::<Vec<_>>()
            .join(", ")
    ));
    warn_left_out(&result, "");
    // The file first: a reader of the table that stops early must not cost the JSON.
    write_json(out, &result)?;
    print_stdout(result.table().trim_end_matches('\n'))
}

/// The NEES warning of docs/theory.md §11 for each filter of an evaluation.
fn warn_left_out(result: &crate::evaluate::Evaluation, context: &str) {
    for f in &result.filters {
        for note in &f.notes {
            warn(format!("{}{context}: {note}", f.name));
        }
        if let Some(a) = f.accuracy.as_ref().filter(|a| a.nees_left_out > 0) {
            warn(format!(
                "NEES of {}{context}: {} of {} terms left out: error and claimed variance both below the resolution floor of f64 (docs/theory.md §11)",
                f.name, a.nees_left_out, a.terms
            ));
        }
    }
}

/// Writes the JSON of `evaluate --out`, when asked for.
fn write_json(out: Option<Output>, value: &impl serde::Serialize) -> Result<()> {
    if let Some(mut out) = out {
        let name = out.name();
        serde_json::to_writer_pretty(&mut out, value).context("writing the evaluation")?;
        std::io::Write::write_all(&mut out, b"\n").map_err(|e| Error::io(&name, e))?;
        out.commit()?;
        info(format!("wrote {name}"));
    }
    Ok(())
}

//! `sisfilt evaluate`: a Monte Carlo comparison of the filters (docs/theory.md §11).

use std::io::{IsTerminal, Write};
use std::path::{Path, PathBuf};

use anyhow::{Context, Result};

use sisfilt::error::Error;
use sisfilt::evaluate::{Compared, Part, Shard, Study};
use sisfilt::io::{MAX_DOCUMENT_BYTES, read_text};
use sisfilt::io::{Output, Role, check_files};
use sisfilt::messages::{Verbosity, info, verbosity, warn};
use sisfilt::model::Model;

use super::choice::choice;
use super::{SetArgs, config_files, in_flag_words, print_line};

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
    /// Write the results as JSON to this file; `-` is standard output, and the table then goes
    /// to standard error.
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Leave the steps t ≤ BURN_IN out of the figures (the initial transient).
    #[arg(long, default_value_t = 0)]
    pub burn_in: usize,
    /// Largest lifted state size N·n for the centralized filters (skipped above it).
    #[arg(long, default_value_t = sisfilt::filter::centralized::DEFAULT_MAX_LIFTED)]
    pub max_lifted: usize,
    /// Largest memory each filter may hold (the centralized filters' lifted matrices, the
    /// joint filters' bands), checked before it is allocated; a filter above it is skipped
    /// with a note: bytes, or with a K, M or G suffix [default: 8G].
    #[arg(long, value_name = "BYTES", value_parser = super::estimate::parse_max_memory)]
    pub max_memory: Option<u64>,
    /// The joint filter's covariance band K.
    #[arg(long, value_name = "K", default_value_t = sisfilt::filter::joint::DEFAULT_BAND)]
    pub band: usize,
    /// The joint filters' diagonal loading ε of the prior band, P_ii += ε max(tr(P_ii)/n, f) I
    /// with a floor f far below any variance that matters (docs/theory.md §8) [default: 1e-9
    /// when every Q is zero or the initial cov is singular, else 0]
    #[arg(long, value_name = "EPS")]
    pub loading: Option<f64>,
    /// Run only these filters (comma-separated; default: all): distributed,
    /// distributed-paper, joint, centralized, centralized-known, naive, with the mixture
    /// update distributed-mixture, joint-mixture, centralized-mixture, and the smoother of
    /// each of the six filters of `estimate` (its name and -smoother, e.g.
    /// joint-mixture-smoother).
    #[arg(
        long,
        value_delimiter = ',',
        value_name = "NAMES",
        value_parser = choice::<Compared>(),
        hide_possible_values = true
    )]
    pub filters: Vec<Compared>,
    /// Also run the smoothers of docs/theory.md §9 (distributed-smoother, joint-smoother,
    /// centralized-smoother and their mixture twins); their RMSE ratio is to the centralized
    /// smoother.
    #[arg(long)]
    pub smooth: bool,
    /// Repeat the evaluation for each arrival probability in this comma-separated list (e.g.
    /// 0.5,0.7,0.9), which replaces the config's p everywhere (`[dropout]` and overrides); the
    /// same seeds serve every value.
    #[arg(long, value_delimiter = ',')]
    pub sweep_p: Option<Vec<f64>>,
    /// Simulate with this arrival probability at every (t, i) while the filters keep the
    /// config's p (or each value of --sweep-p): what a wrong p costs each filter.
    #[arg(long, value_name = "P")]
    pub true_p: Option<f64>,
    /// Run only shard K of M of the study (K = 0..M−1, e.g. $SLURM_ARRAY_TASK_ID/64): its
    /// block of runs with the seeds the whole study gives them, written with --out as a part
    /// that `sisfilt evaluate-merge` adds up with the others.
    #[arg(long, value_name = "K/M", value_parser = parse_shard, requires = "out")]
    pub shard: Option<Shard>,
    #[command(flatten)]
    pub set: SetArgs,
}

/// `sisfilt evaluate-merge`: the parts of a sharded study added up.
#[derive(Debug, clap::Args)]
pub struct MergeArgs {
    /// The parts written by `evaluate --shard K/M --out`, every shard once, in any order.
    #[arg(required = true, value_name = "PART")]
    pub parts: Vec<PathBuf>,
    /// Write the whole study's JSON (as `evaluate --out` writes it) to this file; `-` is
    /// standard output, and the table then goes to standard error.
    #[arg(long)]
    pub out: Option<PathBuf>,
}

/// `K/M` with `K < M`.
fn parse_shard(text: &str) -> std::result::Result<Shard, String> {
    let expected = || {
        format!(
            "expected K/M with 0 ≤ K < M (e.g. 3/64), found `{}`",
            sisfilt::messages::excerpt(text)
        )
    };
    let (k, m) = text.split_once('/').ok_or_else(expected)?;
    let (k, m) = (k.trim().parse(), m.trim().parse());
    let (Ok(k), Ok(m)) = (k, m) else {
        return Err(expected());
    };
    Shard::new(k, m).map_err(|_| expected())
}

/// `sisfilt evaluate`: the table on standard output, the JSON in `--out`.
pub fn run(args: &EvaluateArgs) -> Result<()> {
    let model = Model::load(&args.config, &args.set.set)?;
    if let Some(out) = &args.out {
        check_files(
            &config_files(&args.config, &model),
            &[Role::new("--out", out)],
        )?;
    }
    let out = args.out.as_ref().map(|p| Output::create(p)).transpose()?;
    let opts = sisfilt::evaluate::EvaluateOptions {
        runs: args.runs,
        seed: args.seed.unwrap_or(model.seed),
        burn_in: args.burn_in,
        max_lifted: args.max_lifted,
        band: args.band,
        loading: args.loading,
        filters: args.filters.clone(),
        smooth: args.smooth,
        true_p: args.true_p,
        max_memory: args
            .max_memory
            .unwrap_or(sisfilt::memory::DEFAULT_MAX_MEMORY),
    };
    // The settings go with the name, which the JSON and the figures carry.
    let config_name = std::iter::once(args.config.display().to_string())
        .chain(args.set.set.iter().map(|s| format!("--set {s}")))
        .collect::<Vec<_>>()
        .join(" ");
    let sweep = args.sweep_p.as_deref();
    let shard_runs = args.shard.map_or(args.runs, |s| s.runs(args.runs).len());
    let total_runs = shard_runs * sweep.map_or(1, <[f64]>::len);
    let bar = if std::io::stderr().is_terminal() && verbosity() >= Verbosity::Normal {
        indicatif::ProgressBar::new(total_runs as u64)
    } else {
        indicatif::ProgressBar::hidden()
    };
    info(format!(
        "evaluate: {total_runs} runs of T = {} × N = {} on {} threads",
        model.horizon()?,
        model.subsystems,
        rayon::current_num_threads()
    ));
    let inputs = sisfilt::inputs::RunInputs::of_model(&model)?;
    if let Some(shard) = args.shard {
        let part = sisfilt::evaluate::evaluate_part(
            &model,
            &inputs,
            &config_name,
            opts,
            sweep,
            shard,
            || {
                bar.inc(1);
                Ok(())
            },
        )
        .map_err(in_flag_words)?;
        bar.finish_and_clear();
        info(format!(
            "evaluate: shard {shard}, runs {}..{} of {} in {:.2} s",
            part.runs[0] + 1,
            part.runs[1],
            args.runs,
            part.wall_time_s
        ));
        return write_json(out, &part);
    }
    if let Some(values) = sweep {
        let result =
            sisfilt::evaluate::sweep_p(&model, &inputs, &config_name, opts, values, || {
                bar.inc(1);
                Ok(())
            })
            .map_err(in_flag_words)?;
        bar.finish_and_clear();
        info(format!("evaluate: {:.2} s", result.total_wall_time_s));
        for (p, e) in result.sweep_p.iter().zip(&result.evaluations) {
            warn_left_out(e, &format!(" at p = {p}"));
        }
        write_json(out, &result)?;
        return print_table(args.out.as_deref(), &result.table());
    }
    let result = sisfilt::evaluate::evaluate(&model, &inputs, &config_name, opts, || {
        bar.inc(1);
        Ok(())
    })
    .map_err(in_flag_words)?;
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
    print_table(args.out.as_deref(), &result.table())
}

/// `sisfilt evaluate-merge`: the table of the whole study on standard output, its JSON in
/// `--out`.
pub fn merge(args: &MergeArgs) -> Result<()> {
    let read: Vec<Role> = args
        .parts
        .iter()
        .map(|p| Role::new("a part", p.as_path()))
        .collect();
    if let Some(out) = &args.out {
        check_files(&read, &[Role::new("--out", out)])?;
    }
    let parts = args
        .parts
        .iter()
        .map(|path| {
            let name = path.display().to_string();
            let file = std::fs::File::open(path).map_err(|e| Error::read(path, e))?;
            let text = read_text(&name, file, MAX_DOCUMENT_BYTES, "part")?;
            let part: Part = serde_json::from_str(&text).map_err(|e| {
                Error::json(&name, "a part written by `sisfilt evaluate --shard`", &e)
            })?;
            Ok((name, part))
        })
        .collect::<Result<Vec<_>>>()?;
    let out = args.out.as_ref().map(|p| Output::create(p)).transpose()?;
    let start = std::time::Instant::now();
    let study = sisfilt::evaluate::merge(&parts).map_err(Error::from)?;
    info(format!(
        "evaluate-merge: {} parts in {:.3} s",
        parts.len(),
        start.elapsed().as_secs_f64()
    ));
    match &study {
        Study::Evaluation(e) => warn_left_out(e, ""),
        Study::Sweep(s) => {
            for (p, e) in s.sweep_p.iter().zip(&s.evaluations) {
                warn_left_out(e, &format!(" at p = {p}"));
            }
        }
    }
    write_json(out, &study)?;
    print_table(args.out.as_deref(), &study.table())
}

/// The table on standard output, or, when the JSON takes standard output (`--out -`), on
/// standard error (not with `--quiet`), so that a reader such as `jq` gets the JSON alone.
fn print_table(out: Option<&Path>, table: &str) -> Result<()> {
    let table = table.trim_end_matches('\n');
    if out != Some(Path::new("-")) {
        return print_line(table);
    }
    if verbosity() >= Verbosity::Normal {
        let _ = writeln!(std::io::stderr(), "{table}");
    }
    Ok(())
}

/// The NEES warning of docs/theory.md §11 for each filter of an evaluation.
fn warn_left_out(result: &sisfilt::evaluate::Evaluation, context: &str) {
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

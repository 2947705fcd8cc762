//! `sisfilt fit`: maximum-likelihood estimates of `p` and the diagonals of `Q` and `M` (shared
//! or each subsystem's own) from a measurement file, with intervals (docs/theory.md §16).

use std::io::Write;
use std::path::{Path, PathBuf};

use anyhow::Result;

use sisfilt::config::ConfigSource;
use sisfilt::error::Error;
use sisfilt::filter::{Dropouts, FilterKind};
use sisfilt::fit::{DEFAULT_MAX_ITER, FitProgress, FitSpec, ParamGroup, ReportFormat};
use sisfilt::inputs::{InputStream, open_csv};
use sisfilt::io::{Output, Role, StepLayout, check_files};
use sisfilt::messages::{Verbosity, finding, verbosity, warn};
use sisfilt::model::Model;
use sisfilt::run::FileSource;

use super::choice::choice;
use super::data::{Data, DataArgs};
use super::{SetArgs, in_flag_words, print_stdout};

#[derive(Debug, clap::Args)]
pub struct FitArgs {
    /// The data, and the config whose values are where the fit starts.
    #[command(flatten)]
    pub data: DataArgs,
    /// What to fit, comma-separated: p (one arrival probability for the whole chain), Q and M
    /// (their diagonals, each entry shared by every subsystem; off-diagonal entries stay as
    /// configured), Q[i] and M[i] (each subsystem's own diagonal) [default: p,Q,M; Q,M with
    /// --dropouts known].
    #[arg(long, value_name = "LIST")]
    pub params: Option<String>,
    /// The filter whose log-likelihood is maximised: joint (default) or centralized (exact;
    /// small chains). distributed cannot fit Q (its likelihood ignores the neighbours'
    /// uncertainty, which Q then absorbs).
    #[arg(long, value_parser = choice::<FilterKind>(), default_value = "joint")]
    pub filter: FilterKind,
    /// Joint filter: keep the covariance blocks |i − j| ≤ K [default: the cheapest band whose
    /// log-likelihood is within 0.1 nat of the centralized filter's, or of the next wider band's
    /// on chains too long for it; the centralized filter where that is cheaper].
    #[arg(long, value_name = "K")]
    pub band: Option<usize>,
    /// unknown: the likelihood of the mixture update, which weighs each measurement by the
    /// chance that it arrived (fits p); known: lost elements are empty cells, skipped by the
    /// exact Gaussian likelihood (p does not enter it).
    #[arg(long, value_parser = choice::<Dropouts>(), default_value = "unknown")]
    pub dropouts: Dropouts,
    /// Largest memory the filter may hold, checked before its arrays are allocated: bytes, or
    /// with a K, M or G suffix [default: 8G].
    #[arg(long, value_name = "BYTES", value_parser = super::estimate::parse_max_memory)]
    pub max_memory: Option<u64>,
    /// Iterations of the optimiser (L-BFGS), at most.
    #[arg(long, value_name = "N", default_value_t = DEFAULT_MAX_ITER)]
    pub max_iter: usize,
    /// The report on standard output: a table, or JSON for scripts.
    #[arg(long, value_parser = choice::<ReportFormat>(), default_value = "text")]
    pub format: ReportFormat,
    /// Write the config with the fitted values in place (ready for `estimate` and
    /// `simulate`), atomically.
    #[arg(long, value_name = "FITTED.toml")]
    pub out: Option<PathBuf>,
    #[command(flatten)]
    pub set: SetArgs,
}

impl FitArgs {
    fn spec(&self) -> Result<sisfilt::fit::CheckedFit> {
        let params = match (&self.params, self.dropouts) {
            (Some(list), _) => ParamGroup::parse_list(list).map_err(in_flag_words)?,
            (None, Dropouts::Unknown) => vec![ParamGroup::P, ParamGroup::Q, ParamGroup::M],
            (None, Dropouts::Known) => vec![ParamGroup::Q, ParamGroup::M],
        };
        let spec = FitSpec {
            params,
            filter: self.filter,
            band: self.band,
            dropouts: self.dropouts,
            max_iter: self.max_iter,
            max_memory: self.max_memory,
        };
        Ok(spec.check().map_err(in_flag_words)?)
    }
}

/// `sisfilt fit`: reads the data into memory, fits, prints the report and the fitted model's
/// innovation check, and writes the fitted config.
pub fn run(args: &FitArgs) -> Result<()> {
    let spec = args.spec()?;
    let data = args.data.load(&args.set.set)?;
    let written: Vec<Role> = args.out.iter().map(|p| Role::new("--out", p)).collect();
    check_files(&args.data.roles(&data), &written)?;
    let Data {
        src,
        model,
        inputs_file,
        ..
    } = &data;
    let inputs = InputStream::open(model, inputs_file.as_deref())?;
    let meas = open_csv(
        &args.data.meas,
        StepLayout::measurements(model.dims.q),
        model.subsystems,
    )?;
    let (y, u) = sisfilt::run::read_all(model, &mut FileSource::new(meas, inputs))?;
    // Open the output before the long run, so that a bad path fails fast.
    let output = args.out.as_deref().map(Output::create).transpose()?;

    let progress = (verbosity() >= Verbosity::Normal).then(|| {
        Box::new(|p: &FitProgress| {
            let _ = writeln!(
                std::io::stderr(),
                "fit: iteration {}, log-likelihood {:.6}, {} filter runs",
                p.iteration,
                p.loglik,
                p.evaluations
            );
            Ok(())
        }) as sisfilt::fit::ProgressFn
    });
    let fit = sisfilt::fit::fit(model, &spec, &y, Some(&u), progress).map_err(in_flag_words)?;
    for warning in &fit.report.warnings {
        warn(warning);
    }
    match args.format {
        ReportFormat::Text => print_stdout(fit.report.table().as_bytes())?,
        ReportFormat::Json => {
            let mut text = serde_json::to_string_pretty(&fit.report)
                .map_err(|e| Error::Usage(format!("fit: the report: {e}")))?;
            text.push('\n');
            print_stdout(text.as_bytes())?;
        }
    }
    if let Some(r) = &fit.report.innovations {
        finding("innovations of the fitted model", r.summary());
        for line in r.warnings() {
            warn(line);
        }
    }
    if let (Some(mut output), Some(path)) = (output, args.out.as_deref()) {
        let text = fitted_config_text(src, &fit, &args.data.meas, path)?;
        output
            .write_all(text.as_bytes())
            .map_err(|e| Error::io(path, e))?;
        output.commit()?;
    }
    Ok(())
}

/// The fitted config as TOML, with a header saying where it came from. An inputs file named
/// relative to the config's folder is named by its full path, so that the fitted config
/// reads it wherever it is written; the text must read back as the fitted model.
fn fitted_config_text(
    src: &ConfigSource,
    fit: &sisfilt::fit::Fit,
    meas: &Path,
    out: &Path,
) -> Result<String> {
    let mut raw = fit.fitted_config(&src.raw);
    if let Some(path) = raw.input.as_mut().and_then(|i| i.path.as_mut())
        && Path::new(path.as_str()).is_relative()
    {
        let full = src.dir.join(path.as_str());
        *path = std::fs::canonicalize(&full)
            .unwrap_or(full)
            .display()
            .to_string();
    }
    let name = out.display().to_string();
    let fitted = ConfigSource::from_raw(&name, src.dir.clone(), raw)?;
    let model = Model::from_config(&fitted)?;
    if !model.same_parameters(&fit.model) {
        return Err(Error::Usage(format!(
            "{name}: the fitted config does not read back as the fitted model (please report this)"
        ))
        .into());
    }
    let fitted_names: Vec<&str> = fit
        .report
        .parameters
        .iter()
        .map(|p| p.name.as_str())
        .collect();
    Ok(format!(
        "# Fitted by `sisfilt fit` ({}, {} filter, {} dropouts) to {}: {}.\n# log-likelihood {:.6} (configured {:.6}).\n{}",
        env!("CARGO_PKG_VERSION"),
        fit.report.filter_name(),
        fit.report.dropouts_name(),
        meas.display(),
        fitted_names.join(", "),
        fit.report.loglik,
        fit.report.loglik_start,
        fitted.text.trim_end()
    ) + "\n")
}

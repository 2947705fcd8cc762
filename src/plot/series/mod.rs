//! `sisfilt plot series`: one state element `x_k` of one subsystem `i` against time.
//!
//! The top panel shows the truth, the estimate `x̂_k(t)` with its band `x̂_k ± 2σ_k`
//! (`σ_k² = P_kk`, the reported variance), an optional second estimate (`--smoothed`) with its
//! own band, and the time steps whose measurement was lost (`gamma = 0` in the truth file) as
//! ticks along the time axis. The measurements `y = γ J x + R u + d` (docs/theory.md §1, (P5)) are drawn
//! over the state when some row of `J` picks `x_k` alone and `R` adds nothing to it (then
//! `y_r = x_k + d_r` when the measurement arrived, pure noise when it was lost); otherwise they
//! get a panel of their own. When the estimates carry the mixture update's `π(t, i)` (the
//! `arrival` column, docs/theory.md §10), each measurement is coloured by it: taken
//! (`π ≥ 0.9`), set aside as lost (`π ≤ 0.1`) or in between, so one sees which readings the
//! filter discounted; its shape still tells whether it arrived. The middle panel shows the
//! error `x̂_k − x_k` against `±2σ_k`: for a consistent filter about 95 % of the error lies
//! inside the band.

use std::path::{Path, PathBuf};

use anyhow::Result;

use super::data::{
    EstimatesFile, MeasurementFile, TruthFile, drawable_error, ends_early, file_name, one_based,
    same_chain,
};
use super::{commit_svg, open_output};
use crate::config::ConfigSetting;
use crate::error::Error;
use crate::io::{Role, RunRecord, folder_of};
use crate::messages::warn;
use crate::model::Model;

mod render;
pub use render::render;

/// One estimate of `x_k(t)`, `t = 1..T`, with its reported variance.
pub struct Track {
    /// The file it came from (for the legend).
    pub name: String,
    pub x: Vec<f64>,
    pub var: Vec<f64>,
}

/// The measurements of the subsystem, `t = 1..T`.
pub struct Measured {
    /// `T × q` values, row by row (NaN: an element left empty, `--dropouts known`).
    pub y: Vec<f64>,
    pub q: usize,
    /// The row `r` (0-based) of `J` that picks `x_k` alone, when there is one.
    pub direct: Option<usize>,
    /// Why the measurements are not drawn over the state (when `direct` is `None`).
    pub why_separate: String,
}

/// Everything the figure shows.
pub struct SeriesData {
    /// Subsystem `i` and state element `k`, 1-based.
    pub subsystem: usize,
    pub state: usize,
    /// The steps drawn.
    pub steps: usize,
    /// The true state, with a truth file.
    pub truth: Option<Vec<f64>>,
    /// Whether the measurement of `(t, i)` arrived, with a truth file.
    pub gamma: Option<Vec<bool>>,
    /// Without a truth: the NIS of `(t, i)` from the estimates' `nis` column (docs/theory.md
    /// §14), and the measured elements `q` for its band when known.
    pub nis: Option<Vec<f64>>,
    pub nis_q: Option<usize>,
    /// The estimates' `π(t, i)`, the probability the filter gave to the measurement having
    /// arrived, when they carry it.
    pub arrival: Option<Vec<f64>>,
    pub estimate: Track,
    pub smoothed: Option<Track>,
    pub meas: Option<Measured>,
}

/// What `plot series` draws, from which files, and where.
#[derive(Debug, Clone)]
pub struct SeriesPlot {
    /// Estimates written by `estimate` (CSV or JSON).
    pub estimates: PathBuf,
    /// Truth written by `simulate` (`t,i,x1..xn,gamma`); without it, the second panel shows
    /// the NIS of the estimates' `nis` column instead of the error.
    pub truth: Option<PathBuf>,
    /// Measurements (`t,i,y1..yq`), drawn when given.
    pub meas: Option<PathBuf>,
    /// Second estimates (e.g. smoothed), drawn with their own band.
    pub smoothed: Option<PathBuf>,
    /// The config, to learn `J` (else the run record beside `meas` or `truth`).
    pub config: Option<PathBuf>,
    /// Values over the config's (`--set`).
    pub settings: Vec<ConfigSetting>,
    /// The subsystem `i` (1..N).
    pub subsystem: usize,
    /// The state element `k` (1..n).
    pub state: usize,
    /// The SVG file to write.
    pub out: PathBuf,
}

/// `sisfilt plot series`.
pub fn run(args: &SeriesPlot) -> Result<()> {
    let mut inputs: Vec<Role> = (args.truth.iter().map(|t| Role::new("--truth", t)))
        .chain([Role::new("--estimates", &args.estimates)])
        .collect();
    let optional = [
        ("--smoothed", &args.smoothed),
        ("--meas", &args.meas),
        ("--config", &args.config),
    ];
    for (what, path) in optional {
        if let Some(path) = path {
            inputs.push(Role::new(what, path));
        }
    }
    // Without --config, the model comes from the run record beside the measurements.
    let records: Vec<PathBuf> = match (&args.meas, &args.config) {
        (Some(meas), None) => std::iter::once(meas)
            .chain(args.truth.as_ref())
            .map(|p| folder_of(p).join(RunRecord::FILE))
            .collect(),
        _ => Vec::new(),
    };
    inputs.extend(records.iter().map(|p| Role::new("the run record", p)));
    let out = open_output(&args.out, &inputs)?;
    let data = read(args)?;
    let svg = render(&data)?;
    commit_svg(out, &svg)
}

/// Reads the files of `args` in lock-step and keeps subsystem `i`, state `k`.
pub fn read(args: &SeriesPlot) -> Result<SeriesData> {
    let mut truth = args.truth.as_deref().map(TruthFile::open).transpose()?;
    let mut est = EstimatesFile::open(&args.estimates)?;
    let mut smooth = args
        .smoothed
        .as_deref()
        .map(EstimatesFile::open)
        .transpose()?;
    let mut meas = args
        .meas
        .as_deref()
        .map(MeasurementFile::open)
        .transpose()?;
    if truth.is_some() {
        est.check_against_truth()?;
        smooth
            .as_ref()
            .map_or(Ok(()), EstimatesFile::check_against_truth)?;
    }
    // The file the others are checked against: the truth, else the estimates.
    let (ref_name, n, big_n) = match &truth {
        Some(t) => (t.reader.name().to_string(), t.n, t.subsystems),
        None => (est.name().to_string(), est.n, est.subsystems),
    };
    for e in std::iter::once(&est).chain(smooth.as_ref()) {
        same_chain((e.name(), e.subsystems), (&ref_name, big_n))?;
        if e.n != n {
            return Err(Error::File {
                file: e.name().to_string(),
                msg: format!(
                    "holds n = {} states per subsystem, but {ref_name} holds n = {n}: were they written for the same run?",
                    e.n
                ),
            }
            .into());
        }
    }
    if let Some(m) = &meas {
        same_chain((m.reader.name(), m.subsystems), (&ref_name, big_n))?;
    }
    let i = one_based(
        "--subsystem",
        args.subsystem,
        big_n,
        &format!("{ref_name} holds N = {big_n} subsystems"),
    )?;
    let k = one_based(
        "--state",
        args.state,
        n,
        &format!("{ref_name} holds n = {n} states per subsystem"),
    )?;

    let mut x_true = vec![0.0; truth.as_ref().map_or(0, TruthFile::row_values)];
    let width = est.row_width();
    let mut x_est = vec![0.0; big_n * width];
    let mut x_smooth = vec![0.0; big_n * width];
    let q = meas.as_ref().map_or(0, |m| m.q);
    let mut y = vec![0.0; big_n * q];
    let var_at = est.variance_index(k);
    let nis_at = est.nis_index().filter(|_| truth.is_none());

    let mut data = SeriesData {
        subsystem: args.subsystem,
        state: args.state,
        steps: 0,
        truth: truth.as_ref().map(|_| Vec::new()),
        gamma: truth.as_ref().map(|_| Vec::new()),
        nis: nis_at.map(|_| Vec::new()),
        nis_q: None,
        arrival: est.arrival_index().map(|_| Vec::new()),
        estimate: Track {
            name: file_name(&args.estimates),
            x: vec![],
            var: vec![],
        },
        smoothed: args.smoothed.as_deref().map(|p| Track {
            name: file_name(p),
            x: vec![],
            var: vec![],
        }),
        meas: None,
    };
    let mut y_kept = Vec::new();
    loop {
        let t_est = est.read_step(&mut x_est)?;
        let t_truth = match truth.as_mut() {
            Some(tr) => tr.reader.read_step(&mut x_true)?,
            None => t_est,
        };
        let t = match (t_truth, t_est) {
            (None, None) => break,
            (Some(t), None) => return Err(ends_early(est.name(), &ref_name, t - 1).into()),
            (None, Some(t)) => return Err(ends_early(&ref_name, est.name(), t - 1).into()),
            (Some(t), Some(_)) => t,
        };
        let x_hat = x_est[i * width + k];
        if let (Some(tr), Some(g)) = (data.truth.as_mut(), data.gamma.as_mut()) {
            drawable_error(t, i, x_hat, x_true[i * (n + 1) + k])?;
            tr.push(x_true[i * (n + 1) + k]);
            g.push(x_true[i * (n + 1) + n] != 0.0);
        } else {
            drawable_error(t, i, x_hat, 0.0)?;
        }
        data.estimate.x.push(x_hat);
        data.estimate.var.push(x_est[i * width + var_at]);
        if let (Some(pi), Some(at)) = (data.arrival.as_mut(), est.arrival_index()) {
            pi.push(x_est[i * width + at]);
        }
        if let (Some(v), Some(at)) = (data.nis.as_mut(), nis_at) {
            v.push(x_est[i * width + at]);
        }
        if let (Some(s), Some(track)) = (smooth.as_mut(), data.smoothed.as_mut()) {
            if s.read_step(&mut x_smooth)?.is_none() {
                return Err(ends_early(s.name(), &ref_name, t - 1).into());
            }
            let reference = data.truth.as_ref().map_or(0.0, |tr| tr[t - 1]);
            drawable_error(t, i, x_smooth[i * width + k], reference)?;
            track.x.push(x_smooth[i * width + k]);
            track.var.push(x_smooth[i * width + var_at]);
        }
        if let Some(m) = meas.as_mut() {
            if m.reader.read_step(&mut y)?.is_none() {
                return Err(ends_early(m.reader.name(), &ref_name, t - 1).into());
            }
            y_kept.extend_from_slice(&y[i * q..(i + 1) * q]);
        }
        data.steps = t;
    }
    let steps = data.steps;
    // Every file must end where the reference ends.
    if let Some(s) = smooth.as_mut()
        && s.read_step(&mut x_smooth)?.is_some()
    {
        return Err(ends_early(&ref_name, s.name(), steps).into());
    }
    if let Some(m) = meas.as_mut()
        && m.reader.read_step(&mut y)?.is_some()
    {
        return Err(ends_early(&ref_name, m.reader.name(), steps).into());
    }
    if truth.is_none() && data.nis.is_none() {
        warn(format!(
            "{}: has no `nis` column, so without --truth the figure has no second panel; `sisfilt estimate --nis` writes it",
            est.name()
        ));
    }
    if let Some(meas_path) = &args.meas {
        let model = measurement_model(args, meas_path)?;
        data.nis_q = Some(q);
        let (direct, why_separate) = match model {
            Some(model) => direct_row(&model, q, n, big_n, args.subsystem, k, steps),
            None => (
                None,
                "no config (pass --config, or keep run.json beside the data) to tell which state y measures".into(),
            ),
        };
        data.meas = Some(Measured {
            y: y_kept,
            q,
            direct,
            why_separate,
        });
    } else if let Some(config) = &args.config {
        data.nis_q = Some(Model::load(config, &args.settings)?.dims.q);
    }
    Ok(data)
}

/// The model that says what `y` measures: `--config`, else the `run.json` beside the
/// measurements or the truth. A run record that cannot be used only costs the overlay.
fn measurement_model(args: &SeriesPlot, meas: &Path) -> Result<Option<Model>> {
    if let Some(path) = &args.config {
        return Ok(Some(Model::load(path, &args.settings)?));
    }
    let truth = args.truth.as_deref();
    let mut dirs = vec![folder_of(meas)];
    if let Some(truth) = truth
        && folder_of(truth) != dirs[0]
    {
        dirs.push(folder_of(truth));
    }
    for dir in dirs {
        let record_path = dir.join(RunRecord::FILE);
        let model = RunRecord::load(dir).and_then(|record| match record {
            Some(r) => {
                let src = r
                    .config_source(&record_path)?
                    .with_settings(&args.settings)?;
                Model::from_config(&src).map(Some)
            }
            None => Ok(None),
        });
        match model {
            Ok(Some(m)) => return Ok(Some(m)),
            Ok(None) => {}
            // The user's own --set values must fit the model: bad input, not a lost overlay.
            Err(e) if !args.settings.is_empty() => return Err(e.into()),
            Err(e) => warn(format!(
                "{e}: drawing the measurements in a panel of their own"
            )),
        }
    }
    Ok(None)
}

/// The first row `r` of `J` with `J[r, :] = e_kᵀ` and `R[r, :] = 0` for subsystem `i` at
/// every `t ≤ steps`: then `y_r` measures `x_k` directly.
fn direct_row(
    model: &Model,
    q: usize,
    n: usize,
    subsystems: usize,
    i: usize,
    k: usize,
    steps: usize,
) -> (Option<usize>, String) {
    let d = model.dims;
    if (d.q, d.n, model.subsystems) != (q, n, subsystems) {
        return (
            None,
            format!(
                "the config ({}) has q = {}, n = {}, N = {}, the files q = {q}, n = {n}, N = {subsystems}",
                model.name, d.q, d.n, model.subsystems
            ),
        );
    }
    let windows: Vec<_> = model
        .windows()
        .iter()
        .filter(|w| w.first <= steps.max(1))
        .collect();
    let picks = |r: usize| {
        windows.iter().all(|w| {
            let p = model.param_set(w.ids[i - 1]);
            (0..n).all(|c| p.J[(r, c)] == if c == k { 1.0 } else { 0.0 })
                && (0..d.m).all(|c| p.R[(r, c)] == 0.0)
        })
    };
    match (0..q).find(|&r| picks(r)) {
        Some(r) => (Some(r), String::new()),
        None => (None, format!("no row of J measures x{} alone", k + 1)),
    }
}

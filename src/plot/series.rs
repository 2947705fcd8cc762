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

use std::ops::Range;
use std::path::{Path, PathBuf};

use anyhow::Result;
use plotters::coord::types::RangedCoordf64;
use plotters::prelude::*;
use statrs::distribution::{ChiSquared, ContinuousCDF};

use super::data::{
    EstimatesFile, MeasurementFile, TruthFile, drawable_error, ends_early, file_name, one_based,
    same_chain,
};
use super::{
    Area, CAPTION_SIZE, DESC_SIZE, ESTIMATE, GREY, GRID, LABEL_SIZE, LOST, MEASURED, SMOOTHED,
    Swatch, TITLE_SIZE, TRUTH, WIDTH, commit_svg, draw_centered, draw_legend, fmt_tick, font,
    header_height, legend_lines, open_output, padded, palette,
};
use crate::config::ConfigSetting;
use crate::error::Error;
use crate::io::{Role, RunRecord, folder_of};
use crate::messages::warn;
use crate::model::Model;

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

/// The interval holding `values` (finite ones).
fn extent<'a>(values: impl Iterator<Item = &'a f64>) -> (f64, f64) {
    values
        .filter(|v| v.is_finite())
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), &v| {
            (lo.min(v), hi.max(v))
        })
}

fn union(a: (f64, f64), b: (f64, f64)) -> (f64, f64) {
    (a.0.min(b.0), a.1.max(b.1))
}

const STATE_PANEL: u32 = 470;
const ERROR_PANEL: u32 = 360;
const MEAS_PANEL: u32 = 330;
const TITLE_HEIGHT: u32 = 44;

/// Renders the figure as an SVG document.
pub fn render(d: &SeriesData) -> Result<String> {
    let separate_meas = d.meas.as_ref().filter(|m| m.direct.is_none());
    let second = d.truth.is_some() || d.nis.is_some();
    let height = TITLE_HEIGHT
        + STATE_PANEL
        + if second { ERROR_PANEL } else { 0 }
        + if separate_meas.is_some() {
            MEAS_PANEL
        } else {
            0
        };
    let mut svg = String::new();
    {
        let root = SVGBackend::with_string(&mut svg, (WIDTH, height)).into_drawing_area();
        root.fill(&WHITE)?;
        let (title, rest) = root.split_vertically(TITLE_HEIGHT);
        draw_centered(
            &title,
            &format!(
                "Subsystem {}, state x{}: {} {}",
                d.subsystem,
                d.state,
                std::iter::once(&d.estimate)
                    .chain(d.smoothed.as_ref())
                    .map(|t| t.name.as_str())
                    .collect::<Vec<_>>()
                    .join(" and "),
                if d.truth.is_some() {
                    "against the truth"
                } else {
                    "(no truth: the innovations tell how well the model fits)"
                }
            ),
            12,
            TITLE_SIZE,
        )?;
        let (state_area, rest) = rest.split_vertically(STATE_PANEL);
        let (error_area, meas_area) = rest.split_vertically(if second { ERROR_PANEL } else { 0 });
        state_panel(&state_area, d)?;
        match (&d.truth, &d.gamma, &d.nis) {
            (Some(truth), Some(gamma), _) => error_panel(&error_area, d, truth, gamma)?,
            (None, _, Some(nis)) => nis_panel(&error_area, d, nis)?,
            _ => {}
        }
        if let Some(m) = separate_meas {
            meas_panel(&meas_area, d, m)?;
        }
        root.present()?;
    }
    Ok(svg)
}

/// The lost-measurement ticks: one short vertical line per `t` with `gamma = 0`, in the strip
/// `y0..y1` along the time axis (none without a truth).
fn lost_ticks(
    gamma: Option<&[bool]>,
    y0: f64,
    y1: f64,
) -> impl Iterator<Item = PathElement<(f64, f64)>> {
    gamma
        .unwrap_or_default()
        .iter()
        .enumerate()
        .filter(|(_, g)| !**g)
        .map(move |(t, _)| {
            let t = (t + 1) as f64;
            PathElement::new(vec![(t, y0), (t, y1)], LOST.stroke_width(1))
        })
}

fn time_range(steps: usize) -> Range<f64> {
    padded(1.0, steps.max(2) as f64, 0.01)
}

/// The vertical axis of a panel: its range, and the strip at its bottom that holds the
/// lost-measurement ticks (below the data).
struct ValueAxis {
    range: Range<f64>,
    strip: (f64, f64),
}

/// The vertical axis for data in `lo..hi`; an error when its span overflows f64.
fn with_strip(lo: f64, hi: f64) -> Result<ValueAxis> {
    let y = padded(lo, hi, 0.04);
    let span = y.end - y.start;
    if !span.is_finite() {
        return Err(Error::Usage(format!(
            "the values to draw span {lo:e} to {hi:e}, more than f64 can hold: nothing can be drawn"
        ))
        .into());
    }
    let strip = (y.start - 0.09 * span, y.start - 0.02 * span);
    Ok(ValueAxis {
        range: strip.0 - 0.01 * span..y.end,
        strip,
    })
}

type Chart<'a, 'b> = ChartContext<'a, SVGBackend<'b>, Cartesian2d<RangedCoordf64, RangedCoordf64>>;

/// A chart under a caption and `legend`, with the common axes: time along x, `y_desc` up
/// over `axis`.
fn chart<'a, 'b>(
    area: &'a Area<'b>,
    caption: &str,
    legend: &[(Swatch, String)],
    steps: usize,
    axis: &ValueAxis,
    y_desc: &str,
) -> Result<Chart<'a, 'b>> {
    let strip_top = axis.strip.1;
    // A tick the axis places at zero by adding up steps reads as 0, not as -2.776e-17.
    let rounding = 1e-9 * (axis.range.end - axis.range.start);
    let lines = legend_lines(WIDTH, LEGEND_X, legend);
    let mut ch = ChartBuilder::on(area)
        .margin_top(header_height(lines))
        .margin_left(12)
        .margin_right(24)
        .margin_bottom(6)
        .x_label_area_size(44)
        .y_label_area_size(78)
        .build_cartesian_2d(time_range(steps), axis.range.clone())?;
    ch.configure_mesh()
        .x_desc("time step t")
        .y_desc(y_desc)
        .axis_desc_style(font(DESC_SIZE))
        .label_style(font(LABEL_SIZE))
        .x_label_formatter(&|v| format!("{v:.0}"))
        // No labels in the strip of lost-measurement ticks, which holds no data.
        .y_label_formatter(&|v| {
            if *v < strip_top {
                String::new()
            } else if v.abs() < rounding {
                "0".into()
            } else {
                fmt_tick(*v)
            }
        })
        .x_labels(12)
        .y_labels(8)
        .light_line_style(TRANSPARENT)
        .bold_line_style(GRID)
        .draw()?;
    draw_centered(area, caption, 6, CAPTION_SIZE)?;
    draw_legend(area, LEGEND_X, 46, legend)?;
    Ok(ch)
}

/// Legends start here, in line with the charts' y axes.
const LEGEND_X: i32 = 90;

/// `2σ = 2√var`, with a negative rounding residue read as 0.
fn two_sigma(var: f64) -> f64 {
    2.0 * var.max(0.0).sqrt()
}

/// The filled band `center ± 2σ` as a polygon.
fn band(center: &[f64], var: &[f64], color: RGBColor) -> Polygon<(f64, f64)> {
    let upper = (0..center.len()).map(|t| ((t + 1) as f64, center[t] + two_sigma(var[t])));
    let lower = (0..center.len())
        .rev()
        .map(|t| ((t + 1) as f64, center[t] - two_sigma(var[t])));
    Polygon::new(
        upper.chain(lower).collect::<Vec<_>>(),
        color.mix(0.22).filled(),
    )
}

fn line<DB: DrawingBackend>(
    values: impl Iterator<Item = f64>,
    color: RGBColor,
) -> LineSeries<DB, (f64, f64)> {
    LineSeries::new(
        values.enumerate().map(|(t, v)| ((t + 1) as f64, v)),
        color.stroke_width(2),
    )
}

/// The legend entry of the lost-measurement ticks, with a truth.
fn lost_entry(d: &SeriesData) -> Option<(Swatch, String)> {
    let gamma = d.gamma.as_ref()?;
    let lost = gamma.iter().filter(|g| !**g).count();
    Some((
        Swatch::Tick(LOST),
        format!("measurement lost (γ = 0): {lost} of {} steps", gamma.len()),
    ))
}

/// The estimates drawn, each with its colour: the estimate, and the smoothed one if given.
fn tracks(d: &SeriesData) -> Vec<(&Track, RGBColor)> {
    std::iter::once(&d.estimate)
        .chain(d.smoothed.as_ref())
        .zip([ESTIMATE, SMOOTHED])
        .collect()
}

fn state_panel(area: &Area, d: &SeriesData) -> Result<()> {
    let steps = d.steps;
    let tracks = tracks(d);
    let mut range = extent(d.truth.iter().flatten());
    for (tr, _) in &tracks {
        for t in 0..steps {
            let s = two_sigma(tr.var[t]);
            range = union(range, extent([tr.x[t] - s, tr.x[t] + s].iter()));
        }
    }
    let direct = d.meas.as_ref().and_then(|m| m.direct.map(|r| (m, r)));
    if let Some((m, r)) = direct {
        range = union(range, extent(m.y.iter().skip(r).step_by(m.q)));
    }
    let mut legend: Vec<_> = (d.truth.iter())
        .map(|_| (Swatch::Line(TRUTH), "truth".to_string()))
        .collect();
    for (tr, c) in &tracks {
        legend.push((Swatch::LineBand(*c), format!("{} ± 2σ", tr.name)));
    }
    if let Some((_, r)) = direct {
        legend.extend(measurement_legend(
            d,
            &[(MEASURED, format!("measurement y{}", r + 1))],
        ));
    }
    legend.extend(lost_entry(d));

    let axis = with_strip(range.0, range.1)?;
    let mut ch = chart(
        area,
        &format!(
            "x{} against time: {}estimate and its ±2σ band",
            d.state,
            if d.truth.is_some() { "truth, " } else { "" }
        ),
        &legend,
        steps,
        &axis,
        &format!("x{}", d.state),
    )?;
    for (tr, c) in &tracks {
        ch.draw_series(std::iter::once(band(&tr.x, &tr.var, *c)))?;
    }
    if let Some((m, r)) = direct {
        draw_measurements(&mut ch, d, m, r, MEASURED)?;
    }
    if let Some(truth) = &d.truth {
        ch.draw_series(line(truth.iter().copied(), TRUTH))?;
    }
    for (tr, c) in &tracks {
        ch.draw_series(line(tr.x.iter().copied(), *c))?;
    }
    ch.draw_series(lost_ticks(d.gamma.as_deref(), axis.strip.0, axis.strip.1))?;
    Ok(())
}

fn error_panel(area: &Area, d: &SeriesData, truth: &[f64], gamma: &[bool]) -> Result<()> {
    let steps = d.steps;
    let tracks = tracks(d);
    let mut bound: f64 = 0.0;
    let mut legend = Vec::new();
    for (tr, c) in &tracks {
        let mut inside = 0;
        for t in 0..steps {
            let e = (tr.x[t] - truth[t]).abs();
            let s = two_sigma(tr.var[t]);
            bound = bound.max(if e.is_finite() { e } else { 0.0 });
            bound = bound.max(if s.is_finite() { s } else { 0.0 });
            inside += usize::from(e <= s);
        }
        legend.push((
            Swatch::LineBand(*c),
            format!(
                "error of {}, its ±2σ: {:.1} % inside (95 % if honest)",
                tr.name,
                100.0 * inside as f64 / steps.max(1) as f64
            ),
        ));
    }
    legend.extend(lost_entry(d));
    let axis = with_strip(-bound, bound)?;
    let mut ch = chart(
        area,
        &format!(
            "Estimation error x̂{0} − x{0} against the reported ±2σ",
            d.state
        ),
        &legend,
        steps,
        &axis,
        &format!("x̂{0} − x{0}", d.state),
    )?;
    let zero = vec![0.0; steps];
    // The band is ±2σ around 0, so that one sees whether the error leaves it.
    for (tr, c) in &tracks {
        ch.draw_series(std::iter::once(band(&zero, &tr.var, *c)))?;
    }
    ch.draw_series(std::iter::once(PathElement::new(
        vec![(0.0, 0.0), (steps as f64 + 1.0, 0.0)],
        TRUTH.stroke_width(1),
    )))?;
    for (tr, c) in &tracks {
        ch.draw_series(line((0..steps).map(|t| tr.x[t] - truth[t]), *c))?;
    }
    ch.draw_series(lost_ticks(Some(gamma), axis.strip.0, axis.strip.1))?;
    Ok(())
}

/// Without a truth: the NIS of subsystem `i`'s measurement at each step (docs/theory.md
/// §14), with the 95 % band of `χ²_q` where the number `q` of measured elements is known
/// (the band is exact with known dropouts and close with unknown ones).
fn nis_panel(area: &Area, d: &SeriesData, nis: &[f64]) -> Result<()> {
    let steps = d.steps;
    let band = d.nis_q.and_then(|q| {
        let chi2 = ChiSquared::new(q as f64).ok()?;
        Some((q as f64, chi2.inverse_cdf(0.025), chi2.inverse_cdf(0.975)))
    });
    let finite: Vec<(usize, f64)> = (nis.iter().copied().enumerate())
        .filter(|(_, v)| v.is_finite())
        .collect();
    let mut range = extent(finite.iter().map(|(_, v)| v));
    range.0 = range.0.min(0.0);
    let mut legend = vec![(
        Swatch::Dot(ESTIMATE),
        format!(
            "NIS of y at each step ({} steps without a reading)",
            steps - finite.len()
        ),
    )];
    if let Some((q, low, high)) = band {
        range = union(range, (low, high));
        let inside = finite
            .iter()
            .filter(|(_, v)| low <= *v && *v <= high)
            .count();
        legend.push((
            Swatch::LineBand(GREY),
            format!(
                "95 % band of a model that fits, χ²_{q:.0}: {:.1} % inside; mean {q:.0}",
                100.0 * inside as f64 / finite.len().max(1) as f64
            ),
        ));
    }
    let axis = with_strip(range.0, range.1)?;
    let mut ch = chart(
        area,
        "Normalised innovation squared: each measurement against what the model predicted",
        &legend,
        steps,
        &axis,
        "NIS",
    )?;
    if let Some((q, low, high)) = band {
        let edge = steps as f64 + 1.0;
        ch.draw_series(std::iter::once(Polygon::new(
            vec![(0.0, low), (edge, low), (edge, high), (0.0, high)],
            GREY.mix(0.22).filled(),
        )))?;
        ch.draw_series(std::iter::once(PathElement::new(
            vec![(0.0, q), (edge, q)],
            GREY.stroke_width(1),
        )))?;
    }
    ch.draw_series(
        finite
            .iter()
            .map(|&(t, v)| Circle::new(((t + 1) as f64, v), 2, ESTIMATE.filled())),
    )?;
    Ok(())
}

fn meas_panel(area: &Area, d: &SeriesData, m: &Measured) -> Result<()> {
    let steps = d.steps;
    let range = extent(m.y.iter());
    let color = |r: usize| palette(r + 2);
    let rows: Vec<_> = (0..m.q)
        .map(|r| (color(r), format!("y{}", r + 1)))
        .collect();
    let mut legend = measurement_legend(d, &rows);
    legend.extend(lost_entry(d));
    legend.push((
        Swatch::None,
        format!("Not drawn over x{}: {}.", d.state, m.why_separate),
    ));
    let axis = with_strip(range.0, range.1)?;
    let mut ch = chart(
        area,
        &format!(
            "Measurements y = γ J x + R u + d of subsystem {}",
            d.subsystem
        ),
        &legend,
        steps,
        &axis,
        "y",
    )?;
    for r in 0..m.q {
        draw_measurements(&mut ch, d, m, r, color(r))?;
    }
    ch.draw_series(lost_ticks(d.gamma.as_deref(), axis.strip.0, axis.strip.1))?;
    Ok(())
}

/// A measurement the mixture update set aside as lost (`π ≤ 0.1`), and one it weighed
/// (`0.1 < π < 0.9`); one it took (`π ≥ 0.9`) has the colour of the measurements.
const SET_ASIDE: RGBColor = LOST;
const WEIGHED: RGBColor = RGBColor(240, 170, 0);

/// The colour of a measurement: by `π` when the estimates carry it (the same for every row
/// of `y`, as the legend says), else `arrived` for one that arrived and grey for one that
/// was lost.
fn measurement_color(d: &SeriesData, t: usize, arrived: RGBColor) -> RGBColor {
    match d.arrival.as_ref().map(|pi| pi[t]) {
        Some(pi) if pi <= 0.1 => SET_ASIDE,
        Some(pi) if pi < 0.9 => WEIGHED,
        Some(_) => MEASURED,
        None if arrived_at(d, t) => arrived,
        None => GREY,
    }
}

/// Whether the measurement of step `t` (0-based) arrived; without a truth, taken as arrived.
fn arrived_at(d: &SeriesData, t: usize) -> bool {
    d.gamma.as_ref().is_none_or(|g| g[t])
}

/// The legend of the measurement marks: each row of `y` drawn (its colour and name) for
/// those that arrived (dots), the lost ones (crosses), and with `π` its three colours, each
/// with its count.
fn measurement_legend(d: &SeriesData, rows: &[(RGBColor, String)]) -> Vec<(Swatch, String)> {
    let Some(pi) = &d.arrival else {
        let mut legend: Vec<_> = rows
            .iter()
            .map(|(c, name)| (Swatch::Dot(*c), name.clone()))
            .collect();
        if d.gamma.is_some() {
            legend.push((Swatch::Cross(GREY), "y when lost (noise only)".into()));
        }
        return legend;
    };
    let names: Vec<&str> = rows.iter().map(|(_, name)| name.as_str()).collect();
    let count = |class: RGBColor| {
        (0..pi.len())
            .filter(|&t| measurement_color(d, t, MEASURED) == class)
            .count()
    };
    let shapes = if d.gamma.is_some() {
        " (● arrived, × lost: noise only)"
    } else {
        ""
    };
    vec![
        (Swatch::Dot(GREY), format!("{}{shapes}", names.join(", "))),
        (
            Swatch::Block(MEASURED),
            format!("taken by the filter (π ≥ 0.9): {} steps", count(MEASURED)),
        ),
        (
            Swatch::Block(WEIGHED),
            format!("weighed (0.1 < π < 0.9): {}", count(WEIGHED)),
        ),
        (
            Swatch::Block(SET_ASIDE),
            format!("set aside as lost (π ≤ 0.1): {}", count(SET_ASIDE)),
        ),
    ]
}

/// Row `r` of the measurements: a dot where it arrived, a cross where it was lost, each in
/// [`measurement_color`].
fn draw_measurements(
    ch: &mut Chart<'_, '_>,
    d: &SeriesData,
    m: &Measured,
    r: usize,
    arrived: RGBColor,
) -> Result<()> {
    let marks = (0..d.steps)
        .map(|t| (t, m.y[t * m.q + r]))
        .filter(|(_, v)| v.is_finite());
    for (t, v) in marks {
        let (p, color) = (((t + 1) as f64, v), measurement_color(d, t, arrived));
        if arrived_at(d, t) {
            ch.draw_series(std::iter::once(Circle::new(p, 2, color.filled())))?;
        } else {
            ch.draw_series(std::iter::once(Cross::new(p, 3, color.stroke_width(1))))?;
        }
    }
    Ok(())
}

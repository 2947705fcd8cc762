//! `sisfilt plot heatmap`: the time × subsystem map of the error of one state element, the
//! picture that shows how errors spread along the chain — or, without a truth, of how far
//! each measurement was from what the model predicted, where a broken sensor shows as a
//! stripe.
//!
//! With a truth, each cell holds the normalised error `|x̂_k − x_k| / σ_k` (`σ_k² = P_kk`, the
//! reported variance), or the plain error `|x̂_k − x_k|` with `--plain`. For a consistent
//! filter the normalised error is half-normal: 95 % of the cells lie below 1.96. Without one,
//! each cell holds `√NIS` from the estimates' `nis` column (docs/theory.md §14), whose square
//! averages `q` (the elements measured) for a model that fits. When the chain or the horizon
//! is longer than the picture has room for, a cell stands for a block of `(t, i)` and shows
//! their root mean square (the title says so): for `√NIS`, the root of the average NIS.

use std::path::PathBuf;

use anyhow::Result;
use plotters::prelude::*;

use super::data::{
    EstimatesFile, TruthFile, drawable_error, ends_early, file_name, one_based, same_chain,
};
use super::{
    Area, DESC_SIZE, LABEL_SIZE, TITLE_SIZE, WIDTH, commit_svg, draw_centered, draw_label,
    fmt_tick, font, open_output,
};
use crate::error::Error;
use crate::io::Role;

/// What a map shows at each `(t, i)`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Quantity {
    /// `|x̂_k − x_k| / σ_k`.
    NormalisedError,
    /// `|x̂_k − x_k|`.
    PlainError,
    /// `√NIS` of the measurement (no truth needed).
    Innovation,
}

/// The error of state `k` (or the innovation) at every `(t, i)`.
pub struct ErrorMap {
    pub steps: usize,
    pub subsystems: usize,
    /// State element `k`, 1-based.
    pub state: usize,
    pub quantity: Quantity,
    /// `T × N` values, time-major (`values[(t − 1) N + (i − 1)]`); infinite where a resolved
    /// error meets a zero variance; NaN where a measurement was not received (no NIS).
    pub values: Vec<f64>,
    /// The estimates file's name (for the title).
    pub estimates: String,
}

/// What `plot heatmap` maps, from which files, and where.
#[derive(Debug, Clone)]
pub struct HeatmapPlot {
    /// Estimates written by `estimate` (CSV or JSON).
    pub estimates: PathBuf,
    /// Truth written by `simulate`; without it, the map shows the NIS of the estimates' `nis`
    /// column.
    pub truth: Option<PathBuf>,
    /// The state element `k` (1..n).
    pub state: usize,
    /// Map the plain error `|x̂ − x|` instead of `|x̂ − x| / σ` (with a truth).
    pub plain: bool,
    /// The SVG file to write.
    pub out: PathBuf,
}

/// `sisfilt plot heatmap`.
pub fn run(args: &HeatmapPlot) -> Result<()> {
    let inputs: Vec<Role> = (args.truth.iter().map(|t| Role::new("--truth", t)))
        .chain([Role::new("--estimates", &args.estimates)])
        .collect();
    let out = open_output(&args.out, &inputs)?;
    let map = read(args)?;
    let svg = render(&map)?;
    commit_svg(out, &svg)
}

/// Reads truth and estimates in lock-step, keeping the error of state `k`; without a truth,
/// the estimates' NIS.
pub fn read(args: &HeatmapPlot) -> Result<ErrorMap> {
    let Some(truth_path) = &args.truth else {
        return read_innovations(args);
    };
    let mut truth = TruthFile::open(truth_path)?;
    let mut est = EstimatesFile::open(&args.estimates)?;
    est.check_against_truth()?;
    let truth_name = truth.reader.name().to_string();
    let (n, big_n) = (truth.n, truth.subsystems);
    same_chain((est.name(), est.subsystems), (&truth_name, big_n))?;
    if est.n != n {
        return Err(Error::File {
            file: est.name().to_string(),
            msg: format!(
                "holds n = {} states per subsystem, but {truth_name} holds n = {n}: were they written for the same run?",
                est.n
            ),
        }
        .into());
    }
    let k = one_based(
        "--state",
        args.state,
        n,
        &format!("{truth_name} holds n = {n} states per subsystem"),
    )?;
    let width = est.row_width();
    let var_at = est.variance_index(k);
    let mut x_true = vec![0.0; truth.row_values()];
    let mut x_est = vec![0.0; big_n * width];
    let mut values = Vec::new();
    loop {
        let t_truth = truth.reader.read_step(&mut x_true)?;
        let t_est = est.read_step(&mut x_est)?;
        let t = match (t_truth, t_est) {
            (None, None) => break,
            (Some(t), None) => return Err(ends_early(est.name(), &truth_name, t - 1).into()),
            (None, Some(t)) => return Err(ends_early(&truth_name, est.name(), t - 1).into()),
            (Some(t), Some(_)) => t,
        };
        for i in 0..big_n {
            let e = drawable_error(t, i, x_est[i * width + k], x_true[i * (n + 1) + k])?;
            let v = if args.plain {
                e
            } else {
                let sigma = x_est[i * width + var_at].max(0.0).sqrt();
                match (e == 0.0, sigma == 0.0) {
                    (true, _) => 0.0,
                    (false, true) => f64::INFINITY,
                    (false, false) => e / sigma,
                }
            };
            values.push(v);
        }
    }
    Ok(ErrorMap {
        steps: values.len() / big_n,
        subsystems: big_n,
        state: args.state,
        quantity: if args.plain {
            Quantity::PlainError
        } else {
            Quantity::NormalisedError
        },
        values,
        estimates: file_name(&args.estimates),
    })
}

/// Without a truth: `√NIS` of every `(t, i)` from the estimates' `nis` column.
fn read_innovations(args: &HeatmapPlot) -> Result<ErrorMap> {
    let mut est = EstimatesFile::open(&args.estimates)?;
    if args.plain {
        return Err(Error::Usage(
            "--plain maps the estimation error, which needs --truth; without it the map shows each measurement's NIS".into(),
        )
        .into());
    }
    let at = est.nis_index().ok_or_else(|| Error::File {
        file: est.name().to_string(),
        msg: "has no `nis` column: without --truth the map shows each measurement's NIS, which `sisfilt estimate --nis` writes".into(),
    })?;
    let (width, big_n) = (est.row_width(), est.subsystems);
    let mut row = vec![0.0; big_n * width];
    let mut values = Vec::new();
    while est.read_step(&mut row)?.is_some() {
        values.extend((0..big_n).map(|i| row[i * width + at].sqrt()));
    }
    Ok(ErrorMap {
        steps: values.len() / big_n,
        subsystems: big_n,
        state: args.state,
        quantity: Quantity::Innovation,
        values,
        estimates: file_name(&args.estimates),
    })
}

/// Stops of matplotlib's "viridis" colour map (perceptually uniform, readable in grey and by
/// colour-blind viewers), evenly spaced on `0..=1`.
const VIRIDIS: [(u8, u8, u8); 8] = [
    (68, 1, 84),
    (70, 50, 127),
    (54, 92, 141),
    (39, 127, 143),
    (31, 162, 136),
    (74, 194, 110),
    (160, 219, 57),
    (254, 232, 37),
];

/// The colour of `f ∈ [0, 1]`, interpolated linearly between the [`VIRIDIS`] stops.
fn viridis(f: f64) -> RGBColor {
    let x = f.clamp(0.0, 1.0) * (VIRIDIS.len() - 1) as f64;
    let j = (x.floor() as usize).min(VIRIDIS.len() - 2);
    let w = x - j as f64;
    let (a, b) = (VIRIDIS[j], VIRIDIS[j + 1]);
    let mix = |p: u8, q: u8| (p as f64 + w * (q as f64 - p as f64)).round() as u8;
    RGBColor(mix(a.0, b.0), mix(a.1, b.1), mix(a.2, b.2))
}

/// At most this many cells along time and along the chain, and in all: an SVG of more
/// rectangles grows large without showing more at 100 % zoom.
const MAX_COLUMNS: usize = 400;
const MAX_ROWS: usize = 120;
const MAX_CELLS: usize = 12_000;

/// The colour scale of the map.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Scale {
    /// `0..max`, values above drawn at `max`.
    Linear { max: f64 },
    /// `lo..hi` on a log scale (decades), values outside drawn at the ends.
    Log { lo: f64, hi: f64 },
}

impl Scale {
    /// Position of `v` on the colour bar, in `0..=1`.
    fn fraction(&self, v: f64) -> f64 {
        let f = match *self {
            Scale::Linear { max } => v / max,
            Scale::Log { lo, hi } => {
                if v <= 0.0 {
                    0.0
                } else {
                    (v / lo).ln() / (hi / lo).ln()
                }
            }
        };
        if f.is_nan() { 1.0 } else { f.clamp(0.0, 1.0) }
    }

    /// Tick values of the colour bar.
    fn ticks(&self) -> Vec<f64> {
        match *self {
            Scale::Linear { max } => {
                let step = nice_step(max / 5.0);
                // Counted, not compared with max·(1 + ε), which overflows near f64's limit.
                let last = (max / step + 1e-9).floor().clamp(0.0, 10.0) as usize;
                (0..=last).map(|j| j as f64 * step).collect()
            }
            Scale::Log { lo, hi } => {
                let (a, b) = (lo.log10().round() as i32, hi.log10().round() as i32);
                let every = ((b - a) / 8 + 1).max(1);
                (a..=b)
                    .filter(|e| (e - a) % every == 0)
                    .map(|e| 10f64.powi(e))
                    .collect()
            }
        }
    }

    fn top(&self) -> f64 {
        match *self {
            Scale::Linear { max } => max,
            Scale::Log { hi, .. } => hi,
        }
    }
}

/// The smallest of 1, 2, 2.5, 5 × 10^j not below `v`.
fn nice_step(v: f64) -> f64 {
    if v <= 0.0 || !v.is_finite() {
        return 1.0;
    }
    let base = 10f64.powi(v.log10().floor() as i32);
    for m in [1.0, 2.0, 2.5, 5.0, 10.0] {
        if m * base >= v * (1.0 - 1e-12) {
            return m * base;
        }
    }
    10.0 * base
}

/// `p`-quantile (`0..=1`) of the finite values, by the nearest rank.
fn quantile(sorted: &[f64], p: f64) -> f64 {
    if sorted.is_empty() {
        return 0.0;
    }
    sorted[((sorted.len() - 1) as f64 * p).round() as usize]
}

/// The colour scale for the cell values: the normalised error on `0..3` (or up to its 99th
/// percentile, rounded up) while that stays below 6, else on decades; the plain error on
/// `0..` its 99th percentile, rounded up.
fn choose_scale(cells: &[f64], quantity: Quantity) -> Scale {
    let plain = quantity == Quantity::PlainError;
    let mut finite: Vec<f64> = cells.iter().copied().filter(|v| v.is_finite()).collect();
    finite.sort_by(f64::total_cmp);
    let p99 = quantile(&finite, 0.99);
    if plain {
        return Scale::Linear {
            max: nice_step(p99.max(f64::MIN_POSITIVE)),
        };
    }
    if p99 <= 6.0 {
        return Scale::Linear {
            max: p99.ceil().max(3.0),
        };
    }
    let hi = 10f64.powi(p99.log10().ceil() as i32);
    let p01 = quantile(&finite, 0.01).max(hi * 1e-6);
    let lo = 10f64.powi(p01.log10().floor() as i32).min(0.1);
    Scale::Log { lo, hi }
}

/// Cells of `bt` steps × `bi` subsystems: the root mean square of their values.
struct Binned {
    bt: usize,
    bi: usize,
    columns: usize,
    rows: usize,
    cells: Vec<f64>,
}

fn bin(map: &ErrorMap) -> Binned {
    let bi = map.subsystems.div_ceil(MAX_ROWS);
    let rows = map.subsystems.div_ceil(bi);
    let mut bt = map.steps.div_ceil(MAX_COLUMNS).max(1);
    while map.steps.div_ceil(bt) * rows > MAX_CELLS {
        bt += 1;
    }
    let columns = map.steps.div_ceil(bt);
    let mut sums = vec![0.0; columns * rows];
    let mut counts = vec![0usize; columns * rows];
    for t in 0..map.steps {
        for i in 0..map.subsystems {
            let c = (t / bt) * rows + i / bi;
            let v = map.values[t * map.subsystems + i];
            // A measurement not received has no NIS: its cell counts the others.
            if !v.is_nan() {
                sums[c] += v * v;
                counts[c] += 1;
            }
        }
    }
    // A cell of none: NaN, drawn blank.
    let cells = sums
        .iter()
        .zip(&counts)
        .map(|(s, &c)| {
            if c == 0 {
                f64::NAN
            } else {
                (s / c as f64).sqrt()
            }
        })
        .collect();
    Binned {
        bt,
        bi,
        columns,
        rows,
        cells,
    }
}

const HEIGHT: u32 = 600;
const BAR_WIDTH: u32 = 150;

/// Renders the figure as an SVG document.
pub fn render(map: &ErrorMap) -> Result<String> {
    let binned = bin(map);
    let scale = choose_scale(&binned.cells, map.quantity);
    let k = map.state;
    let (what, quantity) = match map.quantity {
        Quantity::PlainError => ("Estimation error", format!("|x̂{k} − x{k}|")),
        Quantity::NormalisedError => (
            "Normalised estimation error",
            format!("|x̂{k} − x{k}| / σ{k}"),
        ),
        Quantity::Innovation => ("Normalised innovations", "√NIS".to_string()),
    };
    let mut svg = String::new();
    {
        let root = SVGBackend::with_string(&mut svg, (WIDTH, HEIGHT)).into_drawing_area();
        root.fill(&WHITE)?;
        let mut notes = Vec::new();
        if binned.bt > 1 || binned.bi > 1 {
            notes.push(format!(
                "each cell: root mean square over {} step{} × {} subsystem{}",
                binned.bt,
                if binned.bt > 1 { "s" } else { "" },
                binned.bi,
                if binned.bi > 1 { "s" } else { "" }
            ));
        } else {
            notes.push("each cell: one (t, i)".into());
        }
        match map.quantity {
            Quantity::NormalisedError => notes.push(format!(
                "σ{k}² = P{k}_{k}, the reported variance: a consistent filter keeps 95 % of the (t, i) below 1.96"
            )),
            Quantity::Innovation => notes.push(
                "NIS: each measurement against what the model predicted; it averages q (the elements measured) where the model fits, and a faulty sensor shows as a stripe"
                    .into(),
            ),
            Quantity::PlainError => {}
        }
        let blank = binned.cells.iter().filter(|v| v.is_nan()).count();
        if blank > 0 {
            notes.push(format!("{blank} blank cells: no measurement received"));
        }
        let infinite = map.values.iter().filter(|v| v.is_infinite()).count();
        if infinite > 0 {
            notes.push(format!(
                "{infinite} terms with a zero σ and a non-zero error"
            ));
        }
        let (main, bar) = root.split_horizontally(WIDTH - BAR_WIDTH);
        draw_centered(
            &main,
            &format!("{what} {quantity} along the chain ({})", map.estimates),
            12,
            TITLE_SIZE,
        )?;
        for (line, note) in notes.iter().enumerate() {
            draw_centered(&main, note, 42 + 19 * line as i32, LABEL_SIZE)?;
        }
        let mut ch = ChartBuilder::on(&main)
            .margin_top(104)
            .margin_left(12)
            .margin_right(16)
            .margin_bottom(8)
            .x_label_area_size(46)
            .y_label_area_size(64)
            .build_cartesian_2d(
                0.5..map.steps as f64 + 0.5,
                0.5..map.subsystems as f64 + 0.5,
            )?;
        ch.configure_mesh()
            .disable_mesh()
            .x_desc("time step t")
            .y_desc("subsystem i")
            .axis_desc_style(font(DESC_SIZE))
            .label_style(font(LABEL_SIZE))
            .x_labels(12)
            .y_labels(map.subsystems.min(12))
            .x_label_formatter(&|v| integer_label(*v))
            .y_label_formatter(&|v| integer_label(*v))
            .draw()?;
        let (bt, bi, rows) = (binned.bt, binned.bi, binned.rows);
        ch.draw_series((0..binned.columns).flat_map(|c| {
            let cells = &binned.cells;
            (0..rows).map(move |r| {
                let t0 = (c * bt) as f64 + 0.5;
                let t1 = (((c + 1) * bt).min(map.steps)) as f64 + 0.5;
                let i0 = (r * bi) as f64 + 0.5;
                let i1 = (((r + 1) * bi).min(map.subsystems)) as f64 + 0.5;
                let v = cells[c * rows + r];
                let color = if v.is_nan() {
                    WHITE
                } else {
                    viridis(scale.fraction(v))
                };
                Rectangle::new([(t0, i0), (t1, i1)], color.filled())
            })
        }))?;
        color_bar(&bar, scale, &quantity, &binned.cells)?;
        root.present()?;
    }
    Ok(svg)
}

fn integer_label(v: f64) -> String {
    if (v - v.round()).abs() < 1e-9 {
        format!("{v:.0}")
    } else {
        String::new()
    }
}

/// The colour bar: the scale from bottom (0 or `lo`) to top, with ticks and its quantity.
fn color_bar(area: &Area, scale: Scale, quantity: &str, cells: &[f64]) -> Result<()> {
    let (top, bottom) = (112, HEIGHT as i32 - 62);
    let (x0, x1) = (14, 40);
    let steps = 120;
    for s in 0..steps {
        let f0 = s as f64 / steps as f64;
        let f1 = (s + 1) as f64 / steps as f64;
        let y0 = bottom - (f0 * (bottom - top) as f64).round() as i32;
        let y1 = bottom - (f1 * (bottom - top) as f64).round() as i32;
        area.draw(&Rectangle::new(
            [(x0, y1), (x1, y0)],
            viridis((f0 + f1) / 2.0).filled(),
        ))?;
    }
    area.draw(&Rectangle::new(
        [(x0, top), (x1, bottom)],
        BLACK.stroke_width(1),
    ))?;
    for v in scale.ticks() {
        let y = bottom - (scale.fraction(v) * (bottom - top) as f64).round() as i32;
        area.draw(&PathElement::new(vec![(x1, y), (x1 + 5, y)], BLACK))?;
        draw_label(area, fmt_tick(v), (x1 + 8, y))?;
    }
    let clipped = cells.iter().any(|&v| v > scale.top());
    draw_label(area, quantity, (x0, top - 40))?;
    if let Scale::Log { .. } = scale {
        draw_label(area, "(log scale)", (x0, top - 20))?;
    }
    if clipped {
        draw_label(
            area,
            format!("≥ {} drawn", fmt_tick(scale.top())),
            (x0, bottom + 18),
        )?;
        draw_label(area, "at the top", (x0, bottom + 36))?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn nice_steps() {
        assert_eq!(nice_step(0.7), 1.0);
        assert_eq!(nice_step(1.0), 1.0);
        assert_eq!(nice_step(1.2), 2.0);
        assert_eq!(nice_step(2.2), 2.5);
        assert_eq!(nice_step(30.0), 50.0);
        assert_eq!(nice_step(0.031), 0.05);
    }

    /// The linear colour bar's ticks: multiples of the nice step up to the maximum, also
    /// where `max · (1 + ε)` would overflow.
    #[test]
    fn linear_ticks_end_at_the_maximum() {
        let ticks = Scale::Linear { max: 3.0 }.ticks();
        assert_eq!(ticks, vec![0.0, 1.0, 2.0, 3.0]);
        let ticks = Scale::Linear { max: f64::MAX }.ticks();
        assert!((2..=11).contains(&ticks.len()), "{ticks:?}");
        assert!(ticks.iter().all(|v| v.is_finite() && *v <= f64::MAX));
        assert_eq!(Scale::Linear { max: 0.0 }.ticks(), vec![0.0]);
    }

    #[test]
    fn scales() {
        // A consistent filter: half-normal values, 0..3.
        let cells: Vec<f64> = (0..1000).map(|j| 2.6 * j as f64 / 999.0).collect();
        assert_eq!(
            choose_scale(&cells, Quantity::NormalisedError),
            Scale::Linear { max: 3.0 }
        );
        // Overconfident by orders of magnitude: decades.
        let cells: Vec<f64> = (0..1000).map(|j| 10f64.powf(j as f64 / 250.0)).collect();
        let s = choose_scale(&cells, Quantity::NormalisedError);
        assert_eq!(s, Scale::Log { lo: 0.1, hi: 1e4 });
        assert!((s.fraction(1.0) - 0.2).abs() < 1e-12);
        assert_eq!(s.fraction(1e9), 1.0);
        assert_eq!(s.fraction(0.0), 0.0);
        assert_eq!(s.ticks(), vec![0.1, 1.0, 10.0, 100.0, 1000.0, 1e4]);
        assert_eq!(Scale::Linear { max: 3.0 }.ticks(), vec![0.0, 1.0, 2.0, 3.0]);
    }

    #[test]
    fn binning_keeps_rms() {
        let map = ErrorMap {
            steps: 1000,
            subsystems: 30,
            state: 1,
            quantity: Quantity::PlainError,
            values: (0..30_000).map(|j| (j % 7) as f64).collect(),
            estimates: String::new(),
        };
        let b = bin(&map);
        assert!(b.columns * b.rows <= MAX_CELLS);
        assert_eq!(b.rows, 30);
        assert_eq!(b.columns, 1000usize.div_ceil(b.bt));
        // First cell: t < bt, i = 0: values j = t·30, RMS of (30 t mod 7).
        let expect = ((0..b.bt)
            .map(|t| ((30 * t) % 7) as f64)
            .map(|v| v * v)
            .sum::<f64>()
            / b.bt as f64)
            .sqrt();
        assert!((b.cells[0] - expect).abs() < 1e-12);
    }
}

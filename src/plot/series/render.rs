//! The figure of `sisfilt plot series` drawn from its data ([`SeriesData`]): the state panel,
//! the error or NIS panel, and the measurements' panel where they are not drawn over the state.

use std::ops::Range;

use anyhow::Result;
use plotters::coord::types::RangedCoordf64;
use plotters::prelude::*;
use statrs::distribution::{ChiSquared, ContinuousCDF};

use super::{Measured, SeriesData, Track};
use crate::error::Error;
use crate::plot::{
    Area, CAPTION_SIZE, DESC_SIZE, ESTIMATE, GREY, GRID, LABEL_SIZE, LOST, MEASURED, SMOOTHED,
    Swatch, TITLE_SIZE, TRUTH, WIDTH, draw_centered, draw_legend, fmt_tick, font, header_height,
    legend_lines, padded, palette,
};

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

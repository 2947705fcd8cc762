//! `sisfilt plot evaluate`: the figures of a Monte Carlo evaluation (`sisfilt evaluate --out`).
//!
//! For one evaluation: the RMSE of each filter (overall and per state element), and its average
//! NEES (ANEES, `eᵀ P⁻¹ e / n` averaged; 1 for an honest covariance) against the 95 % band of a
//! consistent filter, on a log scale when the values span a decade or more. When the JSON
//! carries, per filter, `nees_per_step` (`nees_per_step[j]` the average NEES at `t = j + 1`,
//! `null` where undefined), a third panel draws it against time. For `evaluate --sweep-p`: RMSE
//! and ANEES against the arrival probability `p`, one curve per filter.

use std::ops::Range;
use std::path::Path;

use anyhow::Result;
use plotters::coord::ranged1d::{AsRangedCoord, ValueFormatter};
use plotters::coord::types::RangedCoordf64;
use plotters::prelude::*;
use plotters::style::text_anchor::{HPos, Pos, VPos};
use serde::Deserialize;
use serde::de::IgnoredAny;

use crate::io::{MAX_DOCUMENT_BYTES, read_text};

use super::data::file_name;
use super::{
    Area, CAPTION_SIZE, DESC_SIZE, GREY, GRID, LABEL_SIZE, Swatch, TITLE_SIZE, WIDTH, commit_svg,
    decade_range, draw_centered, draw_legend, fmt_tick, font, header_height, legend_lines,
    log_axis, open_output, padded, palette,
};
use crate::accuracy::AccuracyReport;
use crate::choice::Choice;
use crate::error::Error;
use crate::evaluate::{EvaluateOptions, Evaluation, FilterResult, Sweep};
use crate::io::Role;

/// The JSON of `evaluate --out`: one evaluation, or a sweep over `p`.
#[derive(Debug)]
enum EvaluationFile {
    Single(Evaluation),
    Sweep(Sweep),
}

impl EvaluationFile {
    fn config(&self) -> &str {
        match self {
            Self::Single(e) => &e.config,
            Self::Sweep(s) => &s.config,
        }
    }

    fn options(&self) -> &EvaluateOptions {
        match self {
            Self::Single(e) => &e.options,
            Self::Sweep(s) => &s.options,
        }
    }
}

/// The average NEES of `f` at each `t = 1..T`, when the evaluation scored any step.
fn nees_per_step(f: &FilterResult) -> Option<&[Option<f64>]> {
    Some(f.nees_per_step.as_slice()).filter(|v| !v.is_empty())
}

/// `sisfilt plot evaluate`: the figure of the JSON `input` (written by `evaluate --out`)
/// into the SVG file `out`.
pub fn run(input: &Path, out: &Path) -> Result<()> {
    let out = open_output(out, &[Role::new("the evaluate JSON", input)])?;
    let doc = read(input)?;
    let svg = render(&doc, input)?;
    commit_svg(out, &svg)
}

fn read(path: &Path) -> Result<EvaluationFile> {
    let name = super::data::display_name(path);
    let text = read_text(
        &name,
        super::data::open(path)?,
        MAX_DOCUMENT_BYTES,
        "evaluation",
    )?;
    let not_eval = |what: String| Error::File {
        file: name.clone(),
        msg: format!("not the JSON of `sisfilt evaluate --out`: {what}"),
    };
    let syntax = |e: serde_json::Error| {
        Error::json(name.clone(), "the JSON of `sisfilt evaluate --out`", &e)
    };
    /// Only whether the document is a sweep.
    #[derive(Deserialize)]
    struct Kind {
        sweep_p: Option<IgnoredAny>,
        filters: Option<IgnoredAny>,
        studies: Option<IgnoredAny>,
    }
    let kind: Kind = serde_json::from_str(&text).map_err(syntax)?;
    if kind.studies.is_some() {
        return Err(not_eval(
            "it is one part of a sharded study (`evaluate --shard`); add the parts up with `sisfilt evaluate-merge PART... --out FILE` and plot that".into(),
        )
        .into());
    }
    match (kind.sweep_p, kind.filters) {
        (Some(_), _) => {
            let sweep: Sweep = serde_json::from_str(&text).map_err(syntax)?;
            if sweep.sweep_p.len() != sweep.evaluations.len() || sweep.sweep_p.is_empty() {
                return Err(not_eval("`sweep_p` and `evaluations` differ in length".into()).into());
            }
            Ok(EvaluationFile::Sweep(sweep))
        }
        (None, Some(_)) => {
            let single: Evaluation = serde_json::from_str(&text).map_err(syntax)?;
            if single.filters.is_empty() {
                return Err(not_eval("its `filters` are empty".into()).into());
            }
            Ok(EvaluationFile::Single(single))
        }
        (None, None) => Err(not_eval("it has neither `filters` nor `sweep_p`".into()).into()),
    }
}

/// Renders the figure of an evaluation or a sweep.
fn render(doc: &EvaluationFile, input: &Path) -> Result<String> {
    match doc {
        EvaluationFile::Sweep(sweep) => render_sweep(doc, sweep, input),
        EvaluationFile::Single(single) => render_single(doc, single, input),
    }
}

fn subtitle(doc: &EvaluationFile, input: &Path) -> String {
    let mut s = format!("{} ({})", doc.config(), file_name(input));
    let o = doc.options();
    s += &format!("; {} Monte Carlo runs", o.runs);
    if o.burn_in > 0 {
        s += &format!(", steps t > {} scored", o.burn_in);
    }
    if let Some(p) = o.true_p {
        let assumed = match doc {
            EvaluationFile::Single(_) => "the config's",
            EvaluationFile::Sweep(_) => "the axis's",
        };
        s += &format!("; simulated with p = {p}, the filters assuming {assumed} p");
    }
    s
}

const TITLE_HEIGHT: u32 = 64;
/// Left margin holding the filter names (the longest, `distributed-mixture-smoother`).
const NAMES_WIDTH: u32 = 250;

fn finite(v: f64) -> Option<f64> {
    v.is_finite().then_some(v)
}

/// Why a filter has no figure: its skip note (without the config's name, which the subtitle
/// gives), or that it overflowed.
fn why_missing(f: &FilterResult, config: &str) -> String {
    match &f.skipped {
        Some(why) => {
            let why = why.replace('\n', " ");
            let why = why
                .strip_prefix(config)
                .and_then(|w| w.strip_prefix(": "))
                .unwrap_or(&why);
            let short: String = why.chars().take(96).collect();
            if short.len() < why.len() {
                format!("skipped: {short}…")
            } else {
                format!("skipped: {short}")
            }
        }
        None => "no figures (estimates overflowed)".into(),
    }
}

fn render_single(doc: &EvaluationFile, single: &Evaluation, input: &Path) -> Result<String> {
    let filters = single.filters.as_slice();
    let n = filters
        .iter()
        .filter_map(|f| f.accuracy.as_ref())
        .map(|a| a.rmse.len())
        .max()
        .unwrap_or(0);
    let group = 14 * (n as u32 + 1) + 18;
    let rmse_height = header_height(1) + 60 + group * filters.len() as u32;
    let anees_height = header_height(2) + 60 + 34 * filters.len() as u32;
    let per_step = filters.iter().any(|f| nees_per_step(f).is_some());
    let per_step_height = if per_step { 380 } else { 0 };
    let height = TITLE_HEIGHT + rmse_height + anees_height + per_step_height;
    let mut svg = String::new();
    {
        let root = SVGBackend::with_string(&mut svg, (WIDTH, height)).into_drawing_area();
        root.fill(&WHITE)?;
        let (title, rest) = root.split_vertically(TITLE_HEIGHT);
        draw_centered(&title, "Accuracy of each filter", 10, TITLE_SIZE)?;
        draw_centered(&title, &subtitle(doc, input), 38, LABEL_SIZE)?;
        let (rmse_area, rest) = rest.split_vertically(rmse_height);
        let (anees_area, step_area) = rest.split_vertically(anees_height);
        rmse_panel(&rmse_area, filters, n, &single.config)?;
        anees_panel(&anees_area, filters, &single.config)?;
        if per_step {
            nees_per_step_panel(&step_area, filters)?;
        }
        root.present()?;
    }
    Ok(svg)
}

/// Colour of state element `k` (0-based), and of the overall RMSE.
fn state_color(k: Option<usize>) -> RGBColor {
    match k {
        None => RGBColor(60, 60, 60),
        Some(k) => palette(k),
    }
}

/// Draws `text` at data point `(x, y)`, shifted by `dx` pixels, vertically centred and
/// aligned by `align` (a filter's name: right-aligned 10 pixels left of the plotting area).
fn text_at<X, Y, DB>(
    ch: &mut ChartContext<DB, Cartesian2d<X, Y>>,
    at: (X::ValueType, Y::ValueType),
    dx: i32,
    align: HPos,
    text: &str,
    color: RGBColor,
) -> Result<()>
where
    X: Ranged,
    Y: Ranged,
    DB: DrawingBackend,
    X::ValueType: Clone,
    Y::ValueType: Clone,
    DB::ErrorType: 'static,
{
    ch.draw_series(std::iter::once(
        EmptyElement::at(at)
            + Text::new(
                text.to_string(),
                (dx, 0),
                font(LABEL_SIZE)
                    .color(&color)
                    .pos(Pos::new(align, VPos::Center)),
            ),
    ))?;
    Ok(())
}

/// Horizontal grouped bars: per filter, the overall RMSE and the RMSE of each state element.
fn rmse_panel(area: &Area, filters: &[FilterResult], n: usize, config: &str) -> Result<()> {
    let values: Vec<f64> = filters
        .iter()
        .filter_map(|f| f.accuracy.as_ref())
        .flat_map(|a| std::iter::once(a.rmse_overall).chain(a.rmse.iter().copied()))
        .filter_map(finite)
        .collect();
    let max = values.iter().copied().fold(0.0, f64::max);
    let min_pos = values
        .iter()
        .copied()
        .filter(|v| *v > 0.0)
        .fold(f64::INFINITY, f64::min);
    let y = 0.0..filters.len() as f64;
    let mut legend = vec![(Swatch::Block(state_color(None)), "overall".to_string())];
    legend.extend((0..n).map(|k| (Swatch::Block(state_color(Some(k))), format!("x{}", k + 1))));
    let header = header_height(legend_lines(WIDTH, NAMES_WIDTH as i32, &legend));
    draw_centered(area, "RMSE (lower is better)", 6, CAPTION_SIZE)?;
    draw_legend(area, NAMES_WIDTH as i32, 46, &legend)?;
    let bars = Bars { filters, n, config };
    // A log scale once the bars span more than two decades (an overflowing or naive filter).
    if max > 0.0 && max / min_pos > 100.0 {
        let x = decade_range(values.iter().copied());
        let base = x.start;
        bars.draw(area, header, log_axis(x), y, base, "RMSE (log scale)")
    } else {
        let x = 0.0..(if max > 0.0 { max * 1.18 } else { 1.0 });
        bars.draw(area, header, x, y, 0.0, "RMSE")
    }
}

/// A chart of one row per filter (names on the left) with its `x` axis, described by `desc`,
/// and its grid drawn.
fn bar_chart<'a, 'b, X>(
    area: &'a Area<'b>,
    header: u32,
    x: X,
    y: Range<f64>,
    desc: &str,
) -> Result<ChartContext<'a, SVGBackend<'b>, Cartesian2d<X::CoordDescType, RangedCoordf64>>>
where
    X: AsRangedCoord<Value = f64>,
    X::CoordDescType: ValueFormatter<f64>,
{
    let mut ch = ChartBuilder::on(area)
        .margin_top(header)
        .margin_left(8)
        .margin_right(30)
        .margin_bottom(6)
        .x_label_area_size(44)
        .y_label_area_size(NAMES_WIDTH)
        .build_cartesian_2d(x, y)?;
    ch.configure_mesh()
        .disable_y_mesh()
        .disable_y_axis()
        .x_desc(desc)
        .axis_desc_style(font(DESC_SIZE))
        .label_style(font(LABEL_SIZE))
        .x_label_formatter(&|v| fmt_tick(*v))
        .light_line_style(TRANSPARENT)
        .bold_line_style(GRID)
        .draw()?;
    Ok(ch)
}

/// The RMSE bars of the filters.
struct Bars<'a> {
    filters: &'a [FilterResult],
    n: usize,
    config: &'a str,
}

impl Bars<'_> {
    fn draw<X>(
        &self,
        area: &Area,
        header: u32,
        x: X,
        y: Range<f64>,
        base: f64,
        desc: &str,
    ) -> Result<()>
    where
        X: AsRangedCoord<Value = f64>,
        X::CoordDescType: ValueFormatter<f64>,
    {
        let rows = self.filters.len();
        let mut ch = bar_chart(area, header, x, y, desc)?;
        let bar = 1.0 / (self.n as f64 + 1.0 + 1.3);
        for (row, f) in self.filters.iter().enumerate() {
            // The first filter on top.
            let centre = (rows - row) as f64 - 0.5;
            let top = (rows - row) as f64 - 0.65 * bar;
            text_at(
                &mut ch,
                (base, centre),
                -10,
                HPos::Right,
                f.name.name(),
                BLACK,
            )?;
            let Some(a) = &f.accuracy else {
                text_at(
                    &mut ch,
                    (base, centre),
                    8,
                    HPos::Left,
                    &why_missing(f, self.config),
                    GREY,
                )?;
                continue;
            };
            let entries = std::iter::once((None, a.rmse_overall))
                .chain(a.rmse.iter().enumerate().map(|(k, v)| (Some(k), *v)));
            for (j, (k, v)) in entries.enumerate() {
                let y1 = top - j as f64 * bar;
                let y0 = y1 - bar * 0.86;
                match finite(v) {
                    Some(v) => {
                        ch.draw_series(std::iter::once(Rectangle::new(
                            [(base, y0), (v, y1)],
                            state_color(k).filled(),
                        )))?;
                        text_at(
                            &mut ch,
                            (v, (y0 + y1) / 2.0),
                            4,
                            HPos::Left,
                            &fmt_value(v),
                            BLACK,
                        )?;
                    }
                    None => {
                        text_at(
                            &mut ch,
                            (base, (y0 + y1) / 2.0),
                            4,
                            HPos::Left,
                            "∞ (overflowed)",
                            GREY,
                        )?;
                    }
                }
            }
        }
        Ok(())
    }
}

/// A figure as printed beside a bar or a dot: four significant digits.
fn fmt_value(v: f64) -> String {
    if v != 0.0 && (v.abs() >= 1e5 || v.abs() < 1e-3) {
        format!("{v:.3e}")
    } else {
        let mag = if v == 0.0 {
            0
        } else {
            v.abs().log10().floor() as i32
        };
        let decimals = (3 - mag).max(0) as usize;
        format!("{v:.decimals$}")
    }
}

/// The ANEES of each filter as a dot, with the 95 % band of a consistent filter and the line
/// ANEES = 1: on a log scale when the values span a decade or more, else linear.
fn anees_panel(area: &Area, filters: &[FilterResult], config: &str) -> Result<()> {
    let mut values: Vec<f64> = vec![1.0];
    for f in filters {
        if let Some(a) = &f.accuracy {
            values.extend(a.anees.and_then(finite));
            values.extend(a.anees_band.into_iter().filter_map(finite));
        }
    }
    let legend = [
        (Swatch::Dot(palette(0)), "ANEES of the filter".to_string()),
        (
            Swatch::Band(GREY),
            "95 % band of a consistent filter (narrow for many terms)".into(),
        ),
        (Swatch::Tick(BLACK), "ANEES = 1: honest covariance".into()),
    ];
    let header = header_height(legend_lines(WIDTH, NAMES_WIDTH as i32, &legend));
    draw_centered(
        area,
        "Average NEES (ANEES): above 1 the filter claims more certainty than it has",
        6,
        CAPTION_SIZE,
    )?;
    draw_legend(area, NAMES_WIDTH as i32, 46, &legend)?;
    let (lo, hi) = values
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &v| {
            (a.min(v), b.max(v))
        });
    let dots = Dots { filters, config };
    if hi / lo >= 10.0 {
        let x = decade_range(values.iter().copied());
        dots.draw(
            area,
            header,
            log_axis(x.clone()),
            x,
            "average NEES (log scale)",
        )
    } else {
        let x = padded(lo, hi, 0.15);
        dots.draw(area, header, x.clone(), x, "average NEES")
    }
}

/// The ANEES dots of the filters.
struct Dots<'a> {
    filters: &'a [FilterResult],
    config: &'a str,
}

impl Dots<'_> {
    fn draw<X>(&self, area: &Area, header: u32, x: X, range: Range<f64>, desc: &str) -> Result<()>
    where
        X: AsRangedCoord<Value = f64>,
        X::CoordDescType: ValueFormatter<f64>,
    {
        let (lo, hi) = (range.start, range.end);
        let rows = self.filters.len();
        let mut ch = bar_chart(area, header, x, 0.0..rows as f64, desc)?;
        ch.draw_series(std::iter::once(PathElement::new(
            vec![(1.0, 0.0), (1.0, rows as f64)],
            BLACK.stroke_width(1),
        )))?;
        for (row, f) in self.filters.iter().enumerate() {
            let y = (rows - row) as f64 - 0.5;
            let color = palette(row);
            text_at(&mut ch, (lo, y), -10, HPos::Right, f.name.name(), BLACK)?;
            let Some(a) = &f.accuracy else {
                text_at(
                    &mut ch,
                    (lo, y),
                    8,
                    HPos::Left,
                    &why_missing(f, self.config),
                    GREY,
                )?;
                continue;
            };
            if let [Some(b0), Some(b1)] = a.anees_band.map(finite) {
                ch.draw_series(std::iter::once(Rectangle::new(
                    [(b0.max(lo), y - 0.3), (b1.min(hi), y + 0.3)],
                    GREY.mix(0.35).filled(),
                )))?;
            }
            match a.anees.and_then(finite) {
                Some(v) => {
                    ch.draw_series(std::iter::once(Circle::new((v, y), 6, color.filled())))?;
                    text_at(&mut ch, (v, y), 10, HPos::Left, &fmt_value(v), BLACK)?;
                }
                None => text_at(
                    &mut ch,
                    (lo, y),
                    8,
                    HPos::Left,
                    "∞: a zero variance met a resolved error",
                    GREY,
                )?,
            }
        }
        Ok(())
    }
}

/// The average NEES against time, one curve per filter, on a log scale.
fn nees_per_step_panel(area: &Area, filters: &[FilterResult]) -> Result<()> {
    let steps = filters
        .iter()
        .filter_map(nees_per_step)
        .map(<[Option<f64>]>::len)
        .max()
        .unwrap_or(1);
    let values = filters
        .iter()
        .filter_map(nees_per_step)
        .flat_map(|v| v.iter().copied().flatten().filter_map(finite))
        .chain([1.0]);
    let y = decade_range(values);
    let mut legend: Vec<(Swatch, String)> = filters
        .iter()
        .enumerate()
        .filter(|(_, f)| nees_per_step(f).is_some())
        .map(|(row, f)| {
            let color = palette(row);
            (Swatch::Line(color), f.name.name().to_string())
        })
        .collect();
    legend.push((Swatch::Line(BLACK), "1 = honest covariance".into()));
    let mut ch = ChartBuilder::on(area)
        .margin_top(header_height(legend_lines(WIDTH, 90, &legend)))
        .margin_left(12)
        .margin_right(30)
        .margin_bottom(6)
        .x_label_area_size(44)
        .y_label_area_size(78)
        .build_cartesian_2d(padded(1.0, steps.max(2) as f64, 0.01), log_axis(y))?;
    ch.configure_mesh()
        .x_desc("time step t")
        .y_desc("average NEES (log scale)")
        .axis_desc_style(font(DESC_SIZE))
        .label_style(font(LABEL_SIZE))
        .x_label_formatter(&|v| format!("{v:.0}"))
        .y_label_formatter(&|v| fmt_tick(*v))
        .light_line_style(TRANSPARENT)
        .bold_line_style(GRID)
        .draw()?;
    ch.draw_series(std::iter::once(PathElement::new(
        vec![(0.0, 1.0), (steps as f64 + 1.0, 1.0)],
        BLACK.stroke_width(1),
    )))?;
    for (row, f) in filters.iter().enumerate() {
        let Some(v) = nees_per_step(f) else { continue };
        let color = palette(row);
        // A gap in the curve where the NEES is undefined (null) or not positive.
        let mut segment: Vec<(f64, f64)> = Vec::new();
        let mut segments = Vec::new();
        for (j, x) in v.iter().enumerate() {
            match x.and_then(finite).filter(|x| *x > 0.0) {
                Some(x) => segment.push(((j + 1) as f64, x)),
                None if !segment.is_empty() => segments.push(std::mem::take(&mut segment)),
                None => {}
            }
        }
        if !segment.is_empty() {
            segments.push(segment);
        }
        ch.draw_series(
            segments
                .into_iter()
                .map(|s| PathElement::new(s, color.stroke_width(2))),
        )?;
    }
    draw_centered(area, "Average NEES at each time step", 6, CAPTION_SIZE)?;
    draw_legend(area, 90, 46, &legend)?;
    Ok(())
}

/// RMSE and ANEES against `p`, one curve per filter.
fn render_sweep(doc: &EvaluationFile, sweep: &Sweep, input: &Path) -> Result<String> {
    let p = &sweep.sweep_p;
    // Filters in the order of the first evaluation.
    let names: Vec<&str> = sweep.evaluations[0]
        .filters
        .iter()
        .map(|f| f.name.name())
        .collect();
    let figure = |e: &Evaluation, name: &str, pick: &dyn Fn(&AccuracyReport) -> Option<f64>| {
        e.filters
            .iter()
            .find(|f| f.name.name() == name)
            .and_then(|f| f.accuracy.as_ref())
            .and_then(pick)
            .and_then(finite)
    };
    let curve = |name: &str, pick: &dyn Fn(&AccuracyReport) -> Option<f64>| -> Vec<(f64, f64)> {
        let mut pts: Vec<(f64, f64)> = p
            .iter()
            .zip(&sweep.evaluations)
            .filter_map(|(&p, e)| figure(e, name, pick).map(|v| (p, v)))
            .collect();
        pts.sort_by(|a, b| a.0.total_cmp(&b.0));
        pts
    };
    let rmse: Vec<Vec<(f64, f64)>> = names
        .iter()
        .map(|n| curve(n, &|a| Some(a.rmse_overall)))
        .collect();
    let anees: Vec<Vec<(f64, f64)>> = names.iter().map(|n| curve(n, &|a| a.anees)).collect();
    let panel = 420;
    let height = TITLE_HEIGHT + 2 * panel;
    let mut svg = String::new();
    {
        let root = SVGBackend::with_string(&mut svg, (WIDTH, height)).into_drawing_area();
        root.fill(&WHITE)?;
        let (title, rest) = root.split_vertically(TITLE_HEIGHT);
        draw_centered(
            &title,
            "Accuracy against the arrival probability p",
            10,
            TITLE_SIZE,
        )?;
        draw_centered(&title, &subtitle(doc, input), 38, LABEL_SIZE)?;
        let (top, bottom) = rest.split_vertically(panel);
        let (p_lo, p_hi) = p
            .iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &v| {
                (a.min(v), b.max(v))
            });
        let x = padded(p_lo, p_hi, 0.04);
        let legend: Vec<(Swatch, String)> = names
            .iter()
            .enumerate()
            .map(|(k, n)| {
                let label = if rmse[k].is_empty() {
                    format!("{n} (no figures)")
                } else {
                    n.to_string()
                };
                (Swatch::Line(palette(k)), label)
            })
            .collect();

        let all_rmse: Vec<f64> = rmse.iter().flatten().map(|pt| pt.1).collect();
        let (r_lo, r_hi) = all_rmse
            .iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &v| {
                (a.min(v), b.max(v))
            });
        if r_lo > 0.0 && r_hi / r_lo > 30.0 {
            sweep_panel(
                &top,
                x.clone(),
                log_axis(decade_range(all_rmse.iter().copied())),
                &rmse,
                "RMSE (log scale)",
                None,
                &legend,
            )?;
        } else {
            let y = if all_rmse.is_empty() {
                0.0..1.0
            } else {
                0.0..r_hi * 1.08
            };
            sweep_panel(&top, x.clone(), y, &rmse, "RMSE (overall)", None, &legend)?;
        }
        draw_centered(&top, "RMSE against p (lower is better)", 6, CAPTION_SIZE)?;

        let all_anees = anees.iter().flatten().map(|pt| pt.1).chain([1.0]);
        sweep_panel(
            &bottom,
            x,
            log_axis(decade_range(all_anees)),
            &anees,
            "average NEES (log scale)",
            Some(1.0),
            &legend,
        )?;
        draw_centered(
            &bottom,
            "Average NEES against p (1 = honest covariance)",
            6,
            CAPTION_SIZE,
        )?;
        root.present()?;
    }
    Ok(svg)
}

fn sweep_panel<Y>(
    area: &Area,
    x: Range<f64>,
    y: Y,
    curves: &[Vec<(f64, f64)>],
    y_desc: &str,
    reference: Option<f64>,
    legend: &[(Swatch, String)],
) -> Result<()>
where
    Y: AsRangedCoord<Value = f64>,
    Y::CoordDescType: ValueFormatter<f64>,
{
    let (x0, x1) = (x.start, x.end);
    draw_legend(area, 90, 46, legend)?;
    let mut ch = ChartBuilder::on(area)
        .margin_top(header_height(legend_lines(WIDTH, 90, legend)))
        .margin_left(12)
        .margin_right(30)
        .margin_bottom(6)
        .x_label_area_size(44)
        .y_label_area_size(78)
        .build_cartesian_2d(x, y)?;
    ch.configure_mesh()
        .x_desc("arrival probability p")
        .y_desc(y_desc)
        .axis_desc_style(font(DESC_SIZE))
        .label_style(font(LABEL_SIZE))
        .x_label_formatter(&|v| fmt_tick(*v))
        .y_label_formatter(&|v| fmt_tick(*v))
        .light_line_style(TRANSPARENT)
        .bold_line_style(GRID)
        .draw()?;
    if let Some(r) = reference {
        ch.draw_series(std::iter::once(PathElement::new(
            vec![(x0, r), (x1, r)],
            BLACK.stroke_width(1),
        )))?;
    }
    for (k, pts) in curves.iter().enumerate() {
        let color = palette(k);
        ch.draw_series(LineSeries::new(pts.iter().copied(), color.stroke_width(2)))?;
        ch.draw_series(pts.iter().map(|&pt| Circle::new(pt, 4, color.filled())))?;
    }
    Ok(())
}

//! SVG figures (docs/theory.md §13 `plot`) drawn from the files the other commands write: one state of
//! one subsystem against time ([`series`]), the time × subsystem map of the estimation error
//! ([`heatmap`]), and the Monte Carlo figures of `evaluate` ([`evaluate`]).
//!
//! Figures are drawn with plotters' SVG backend alone (no font library: text is left to the
//! SVG viewer, and label sizes are estimated), are written atomically, and depend only on
//! their input files: the same input gives the same bytes.

pub mod data;
pub mod evaluate;
pub mod heatmap;
pub mod series;

use std::ops::Range;
use std::path::Path;

use anyhow::Result;
use plotters::coord::Shift;
use plotters::prelude::*;
use plotters::style::text_anchor::{HPos, Pos, VPos};

use crate::io::{Output, Role, check_files};
use crate::messages::info;

/// The font family of every text: the viewer's default sans-serif face.
pub(crate) const FONT: &str = "sans-serif";
/// Width of every figure (pixels).
pub(crate) const WIDTH: u32 = 1000;
/// Font sizes: figure title, panel caption, axis description, tick and legend labels. (The
/// SVG backend writes `font-size` = size / 1.24: 17 gives 13.7 px, readable at 100 %.)
pub(crate) const TITLE_SIZE: f64 = 25.0;
pub(crate) const CAPTION_SIZE: f64 = 21.0;
pub(crate) const DESC_SIZE: f64 = 19.0;
pub(crate) const LABEL_SIZE: f64 = 17.0;

/// The drawing area every figure draws on.
pub(crate) type Area<'a> = DrawingArea<SVGBackend<'a>, Shift>;

/// Colours of data kinds, the same in every figure.
pub(crate) const TRUTH: RGBColor = RGBColor(0, 0, 0);
pub(crate) const ESTIMATE: RGBColor = RGBColor(31, 119, 180);
pub(crate) const SMOOTHED: RGBColor = RGBColor(230, 110, 0);
pub(crate) const MEASURED: RGBColor = RGBColor(44, 160, 44);
pub(crate) const LOST: RGBColor = RGBColor(214, 39, 40);
pub(crate) const GREY: RGBColor = RGBColor(140, 140, 140);
pub(crate) const GRID: RGBColor = RGBColor(225, 225, 225);

/// Colours of curves in figure order (the "tab10" palette).
pub(crate) const PALETTE: [RGBColor; 10] = [
    RGBColor(31, 119, 180),
    RGBColor(255, 127, 14),
    RGBColor(44, 160, 44),
    RGBColor(148, 103, 189),
    RGBColor(214, 39, 40),
    RGBColor(140, 86, 75),
    RGBColor(227, 119, 194),
    RGBColor(127, 127, 127),
    RGBColor(188, 189, 34),
    RGBColor(23, 190, 207),
];

/// The colour of curve `k`: the palette, then its colours darkened by half for the next ten
/// (`evaluate --smooth` compares fifteen filters), and so on.
pub(crate) fn palette(k: usize) -> RGBColor {
    let RGBColor(r, g, b) = PALETTE[k % PALETTE.len()];
    if (k / PALETTE.len()).is_multiple_of(2) {
        RGBColor(r, g, b)
    } else {
        RGBColor(r / 2, g / 2, b / 2)
    }
}

/// Writes a rendered SVG atomically to `out` (opened by the caller before the work, so that a
/// bad path fails fast).
pub(crate) fn commit_svg(mut out: Output, svg: &str) -> Result<()> {
    let svg = compact(svg);
    let name = out.name();
    std::io::Write::write_all(&mut out, svg.as_bytes())
        .map_err(|e| crate::Error::io(name.clone(), e))?;
    out.commit()?;
    info(format!("wrote {name} ({} bytes)", svg.len()));
    Ok(())
}

/// `svg` without the attributes that only restate SVG's defaults (`opacity="1"`, and
/// `stroke="none"`, the initial value of `stroke`): a heat map of thousands of cells shrinks by
/// a quarter.
fn compact(svg: &str) -> String {
    svg.replace(" opacity=\"1\"", "")
        .replace(" stroke=\"none\" stroke-width=\"1\"", "")
        .replace(" stroke=\"none\"", "")
}

/// Opens the output of a figure: a file written atomically, or `-` for standard output
/// (for pipelines such as `… --out - | rsvg-convert`); refused when it is one of the files
/// the figure is drawn from.
pub(crate) fn open_output(path: &Path, inputs: &[Role]) -> Result<Output> {
    check_files(inputs, &[Role::new("--out", path)])?;
    Ok(Output::create(path)?)
}

/// A tick label: up to four significant digits, no trailing zeros; powers of ten beyond
/// `[1e-3, 1e5)`.
pub(crate) fn fmt_tick(v: f64) -> String {
    if v == 0.0 || !v.is_finite() {
        return if v == 0.0 { "0".into() } else { format!("{v}") };
    }
    let mag = v.abs().log10().floor();
    if !(-3.0..5.0).contains(&mag) {
        let s = format!("{v:.3e}");
        let (mantissa, exp) = s.split_once('e').expect("exponent form");
        let mantissa = mantissa.trim_end_matches('0').trim_end_matches('.');
        return format!("{mantissa}e{exp}");
    }
    let decimals = (3.0 - mag).max(0.0) as usize;
    let s = format!("{v:.decimals$}");
    if s.contains('.') {
        s.trim_end_matches('0').trim_end_matches('.').to_string()
    } else {
        s
    }
}

/// `lo..hi` widened by `pad` of its span on both sides (a unit span around a constant).
pub(crate) fn padded(lo: f64, hi: f64, pad: f64) -> Range<f64> {
    if !(lo.is_finite() && hi.is_finite()) {
        return 0.0..1.0;
    }
    if hi <= lo {
        let half = if lo == 0.0 { 1.0 } else { lo.abs() * 0.1 };
        return lo - half..hi + half;
    }
    let d = (hi - lo) * pad;
    lo - d..hi + d
}

/// A log axis over `range`, widened by a hair so that plotters labels the decades at both
/// ends (its first tick is `10^ceil(log10(start))`, computed in floating point).
pub(crate) fn log_axis(range: Range<f64>) -> LogCoord<f64> {
    (range.start * (1.0 - 1e-9)..range.end * (1.0 + 1e-9))
        .log_scale()
        .into()
}

/// The decades `10^a..10^b` that hold every positive value of `values` (at least one decade).
pub(crate) fn decade_range(values: impl Iterator<Item = f64>) -> Range<f64> {
    let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
    for v in values.filter(|v| v.is_finite() && *v > 0.0) {
        lo = lo.min(v);
        hi = hi.max(v);
    }
    if !lo.is_finite() {
        return 0.1..10.0;
    }
    let a = lo.log10().floor() as i32;
    let b = (hi.log10().ceil() as i32).max(a + 1);
    10f64.powi(a)..10f64.powi(b)
}

/// A text style of the figure font.
pub(crate) fn font(size: f64) -> TextStyle<'static> {
    TextStyle::from((FONT, size).into_font())
}

/// Estimated width of `text` in pixels at `size` (the SVG viewer picks the real font).
pub(crate) fn text_width(text: &str, size: f64) -> i32 {
    (text.chars().count() as f64 * size / 1.24 * 0.56).ceil() as i32
}

/// Draws `text` centred at the top of `area`, `y` pixels down.
pub(crate) fn draw_centered(area: &Area, text: &str, y: i32, size: f64) -> Result<()> {
    let (w, _) = area.dim_in_pixel();
    area.draw(&Text::new(
        text.to_string(),
        (w as i32 / 2, y),
        font(size).pos(Pos::new(HPos::Center, VPos::Top)),
    ))?;
    Ok(())
}

/// Draws a label whose left edge and vertical centre are at `at` (pixels).
pub(crate) fn draw_label(area: &Area, text: impl Into<String>, at: (i32, i32)) -> Result<()> {
    area.draw(&Text::new(
        text.into(),
        at,
        font(LABEL_SIZE).pos(Pos::new(HPos::Left, VPos::Center)),
    ))?;
    Ok(())
}

/// Height of a legend line (pixels).
pub(crate) const LEGEND_LINE: i32 = 22;

/// How a legend entry is drawn.
#[derive(Clone, Copy)]
pub(crate) enum Swatch {
    Line(RGBColor),
    /// A line over its band.
    LineBand(RGBColor),
    Band(RGBColor),
    Dot(RGBColor),
    Cross(RGBColor),
    Tick(RGBColor),
    Block(RGBColor),
    /// No symbol: a note.
    None,
}

/// Where each legend entry goes: `(x, line)` with `line` counted from 0, entries side by side
/// from `x` and wrapped before the right edge of a figure `width` pixels wide.
fn legend_layout(width: u32, x: i32, entries: &[(Swatch, String)]) -> Vec<(i32, i32)> {
    let (mut cx, mut line) = (x, 0);
    let mut out = Vec::with_capacity(entries.len());
    for (swatch, label) in entries {
        let needed = swatch_width(swatch) + text_width(label, LABEL_SIZE) + 26;
        if cx + needed > width as i32 - 10 && cx > x {
            cx = x;
            line += 1;
        }
        out.push((cx, line));
        cx += needed;
    }
    out
}

fn swatch_width(swatch: &Swatch) -> i32 {
    if matches!(swatch, Swatch::None) {
        0
    } else {
        30
    }
}

/// The lines a legend takes in a figure `width` pixels wide, starting at `x`.
pub(crate) fn legend_lines(width: u32, x: i32, entries: &[(Swatch, String)]) -> i32 {
    legend_layout(width, x, entries)
        .last()
        .map_or(0, |(_, line)| line + 1)
}

/// Space above a chart for a caption and a legend of `lines` lines (pixels).
pub(crate) fn header_height(lines: i32) -> u32 {
    (40 + lines * LEGEND_LINE + 8) as u32
}

/// Draws a legend, entries side by side from `(x, y)` (the first line's vertical centre), in
/// `area` coordinates, wrapping onto further lines as [`legend_lines`] counts them.
pub(crate) fn draw_legend(area: &Area, x: i32, y: i32, entries: &[(Swatch, String)]) -> Result<()> {
    let (w, _) = area.dim_in_pixel();
    for ((swatch, label), (cx, line)) in entries.iter().zip(legend_layout(w, x, entries)) {
        let cy = y + line * LEGEND_LINE;
        match *swatch {
            Swatch::Line(c) => {
                area.draw(&PathElement::new(
                    vec![(cx, cy), (cx + 24, cy)],
                    c.stroke_width(2),
                ))?;
            }
            Swatch::LineBand(c) => {
                area.draw(&Rectangle::new(
                    [(cx, cy - 7), (cx + 24, cy + 7)],
                    c.mix(0.25).filled(),
                ))?;
                area.draw(&PathElement::new(
                    vec![(cx, cy), (cx + 24, cy)],
                    c.stroke_width(2),
                ))?;
            }
            Swatch::Band(c) => {
                area.draw(&Rectangle::new(
                    [(cx, cy - 7), (cx + 24, cy + 7)],
                    c.mix(0.25).filled(),
                ))?;
            }
            Swatch::Dot(c) => {
                area.draw(&Circle::new((cx + 12, cy), 3, c.filled()))?;
            }
            Swatch::Cross(c) => {
                area.draw(&Cross::new((cx + 12, cy), 4, c.stroke_width(1)))?;
            }
            Swatch::Tick(c) => {
                area.draw(&PathElement::new(
                    vec![(cx + 12, cy - 7), (cx + 12, cy + 7)],
                    c.stroke_width(2),
                ))?;
            }
            Swatch::Block(c) => {
                area.draw(&Rectangle::new(
                    [(cx + 4, cy - 7), (cx + 20, cy + 7)],
                    c.filled(),
                ))?;
            }
            Swatch::None => {}
        }
        draw_label(area, label.clone(), (cx + swatch_width(swatch), cy))?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tick_labels() {
        assert_eq!(fmt_tick(0.0), "0");
        assert_eq!(fmt_tick(0.30000000000000004), "0.3");
        assert_eq!(fmt_tick(-1.5), "-1.5");
        assert_eq!(fmt_tick(200.0), "200");
        assert_eq!(fmt_tick(0.0125), "0.0125");
        assert_eq!(fmt_tick(1e5), "1e5");
        assert_eq!(fmt_tick(2.5e-4), "2.5e-4");
    }

    #[test]
    fn compact_drops_only_defaults() {
        let svg = r##"<rect x="1" opacity="1" fill="#FFFFFF" stroke="none"/><circle opacity="0.5" fill="none" stroke="none" stroke-width="1"/><line opacity="1" stroke="#000000" stroke-width="1"/>"##;
        assert_eq!(
            compact(svg),
            r##"<rect x="1" fill="#FFFFFF"/><circle opacity="0.5" fill="none"/><line stroke="#000000" stroke-width="1"/>"##
        );
    }

    #[test]
    fn decades() {
        assert_eq!(decade_range([0.5, 3.0].into_iter()), 0.1..10.0);
        assert_eq!(
            decade_range([1.0, 1e4, -1.0, f64::NAN].into_iter()),
            1.0..1e4
        );
        assert_eq!(decade_range([2.0].into_iter()), 1.0..10.0);
    }
}

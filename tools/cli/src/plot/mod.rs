//! PNG pictures: trajectories against the truth ([`trajectory_figure`]), radargrams
//! ([`radargram()`]), errors over time with their distribution ([`error_figure`]) and plain
//! charts ([`chart`]).

mod radargram;
mod trajectory;

pub use radargram::{Colormap, Feature, Radargram, radargram, usable_distances};
pub use trajectory::{Lines, RunTrack, TrajectoryFigure, trajectory_figure};

use std::ops::Range;
use std::path::Path;

use anyhow::{Context, Result, anyhow};
use plotters::coord::Shift;
use plotters::coord::types::RangedCoordf64;
use plotters::prelude::*;

/// Where Debian, Fedora and Arch put DejaVu Sans (Debian package `fonts-dejavu-core`).
const FONT_CANDIDATES: [&str; 4] = [
    "/usr/share/fonts/truetype/dejavu/DejaVuSans.ttf",
    "/usr/share/fonts/dejavu/DejaVuSans.ttf",
    "/usr/share/fonts/TTF/DejaVuSans.ttf",
    "/usr/share/fonts/dejavu-sans-fonts/DejaVuSans.ttf",
];

pub(crate) fn register_font() -> Result<()> {
    static REGISTERED: std::sync::OnceLock<Result<(), String>> = std::sync::OnceLock::new();
    REGISTERED
        .get_or_init(|| {
            let path = FONT_CANDIDATES.iter().find(|p| Path::new(p).exists()).ok_or_else(|| {
                format!(
                    "no font for plot labels (looked for {}); install fonts-dejavu-core",
                    FONT_CANDIDATES.join(", ")
                )
            })?;
            let bytes: &'static [u8] = Box::leak(
                std::fs::read(path)
                    .map_err(|e| format!("{path}: {e}"))?
                    .into_boxed_slice(),
            );
            plotters::style::register_font("sans-serif", FontStyle::Normal, bytes)
                .map_err(|_| format!("{path}: not a usable font"))
        })
        .clone()
        .map_err(|e| anyhow!(e))
}

/// A named series of points.
#[derive(Debug, Clone)]
pub struct Series {
    /// Legend label.
    pub label: String,
    /// Points (x, y).
    pub points: Vec<(f64, f64)>,
}

/// The empirical CDF of `values`' magnitudes: (|value|, fraction at or below it), sorted.
#[must_use]
pub fn cdf(values: &[f64]) -> Vec<(f64, f64)> {
    let mut v: Vec<f64> = values.iter().map(|x| x.abs()).filter(|x| x.is_finite()).collect();
    v.sort_by(f64::total_cmp);
    let n = v.len() as f64;
    v.into_iter()
        .enumerate()
        .map(|(i, x)| (x, (i + 1) as f64 / n))
        .collect()
}

/// The box around every point of `series` with 5 % margins ((0, 1, 0, 1) when empty).
pub(crate) fn bounds(series: &[&Series]) -> (f64, f64, f64, f64) {
    let mut b = (f64::INFINITY, f64::NEG_INFINITY, f64::INFINITY, f64::NEG_INFINITY);
    for s in series {
        for &(x, y) in &s.points {
            b = (b.0.min(x), b.1.max(x), b.2.min(y), b.3.max(y));
        }
    }
    if !b.0.is_finite() {
        return (0.0, 1.0, 0.0, 1.0);
    }
    let (px, py) = (0.05 * (b.1 - b.0).max(1e-3), 0.05 * (b.3 - b.2).max(1e-3));
    (b.0 - px, b.1 + px, b.2 - py, b.3 + py)
}

pub(crate) const COLORS: [RGBColor; 5] = [
    RGBColor(0, 0, 0),
    RGBColor(214, 39, 40),
    RGBColor(31, 119, 180),
    RGBColor(44, 160, 44),
    RGBColor(148, 103, 189),
];

/// The error of drawing into `path`'s image, naming the file.
pub(crate) fn draw_err(path: &Path) -> impl Fn(&dyn std::fmt::Display) -> anyhow::Error + '_ {
    move |e| anyhow!("{}: {e}", path.display())
}

/// A chart with plain axes.
pub(crate) type Chart<'a, 'b> = ChartContext<'a, BitMapBackend<'b>, Cartesian2d<RangedCoordf64, RangedCoordf64>>;

/// One panel of a figure into `area`: `caption`, axes over `x` and `y` described by `desc`
/// (`y_label_px` wide for the y labels), and their mesh drawn.
///
/// # Errors
/// The image cannot be drawn.
pub(crate) fn panel<'a, 'b>(
    area: &'a DrawingArea<BitMapBackend<'b>, Shift>,
    path: &Path,
    caption: &str,
    (x, y): (Range<f64>, Range<f64>),
    [x_desc, y_desc]: [&str; 2],
    y_label_px: u32,
) -> Result<Chart<'a, 'b>> {
    let draw = draw_err(path);
    let mut chart = ChartBuilder::on(area)
        .margin(12)
        .caption(caption, ("sans-serif", 18))
        .x_label_area_size(36)
        .y_label_area_size(y_label_px)
        .build_cartesian_2d(x, y)
        .map_err(|e| draw(&e))?;
    chart
        .configure_mesh()
        .x_desc(x_desc)
        .y_desc(y_desc)
        .draw()
        .map_err(|e| draw(&e))?;
    Ok(chart)
}

/// Draws the legend of `chart` on a light box, at `position` (plotters' own place when
/// `None`).
///
/// # Errors
/// The image cannot be drawn.
pub(crate) fn legend<'a, 'b: 'a>(
    chart: &mut Chart<'a, 'b>,
    path: &Path,
    position: Option<SeriesLabelPosition>,
) -> Result<()> {
    let mut labels = chart.configure_series_labels();
    if let Some(position) = position {
        labels.position(position);
    }
    labels
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .draw()
        .map_err(|e| draw_err(path)(&e))
}

/// How [`chart`] draws a series.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Style {
    /// Joined by lines.
    Lines,
    /// Small dots.
    Points,
}

/// One chart of `series` (the first drawn first), axes labelled `x_desc` and `y_desc`, into
/// a PNG.
///
/// # Errors
/// No font for labels, or the image cannot be written.
pub fn chart(path: &Path, title: &str, x_desc: &str, y_desc: &str, series: &[(Series, Style)]) -> Result<()> {
    register_font()?;
    let root = BitMapBackend::new(path, (900, 600)).into_drawing_area();
    let draw = draw_err(path);
    root.fill(&WHITE).map_err(|e| draw(&e))?;
    let (x0, x1, y0, y1) = bounds(&series.iter().map(|(s, _)| s).collect::<Vec<_>>());
    let mut chart = ChartBuilder::on(&root)
        .margin(14)
        .caption(title, ("sans-serif", 20))
        .x_label_area_size(40)
        .y_label_area_size(60)
        .build_cartesian_2d(x0..x1, y0.min(0.0)..y1)
        .map_err(|e| draw(&e))?;
    chart
        .configure_mesh()
        .x_desc(x_desc)
        .y_desc(y_desc)
        .draw()
        .map_err(|e| draw(&e))?;
    for (i, (s, style)) in series.iter().enumerate() {
        let color = COLORS[(i + 1) % COLORS.len()];
        let anno = match style {
            Style::Lines => chart
                .draw_series(LineSeries::new(s.points.iter().copied(), color.stroke_width(2)))
                .map_err(|e| draw(&e))?,
            Style::Points => chart
                .draw_series(s.points.iter().map(|&p| Circle::new(p, 1, color.mix(0.5).filled())))
                .map_err(|e| draw(&e))?,
        };
        anno.label(s.label.clone())
            .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 18, y)], color.stroke_width(2)));
    }
    legend(&mut chart, path, None)?;
    root.present()
        .with_context(|| format!("{}: cannot write", path.display()))?;
    Ok(())
}

/// Draws the CDF of each named series' magnitudes into `area` (`text`: caption, x and y
/// descriptions), in the series colours ([`COLORS`] from the second on), the x axis from 0
/// to the largest magnitude (at least `floor`) plus 5 %.
///
/// # Errors
/// The image cannot be drawn.
pub(crate) fn cdf_panel(
    area: &DrawingArea<BitMapBackend<'_>, Shift>,
    path: &Path,
    [caption, x_desc, y_desc]: [&str; 3],
    magnitudes: &[(String, Vec<f64>)],
    floor: f64,
) -> Result<()> {
    let draw = draw_err(path);
    let curves: Vec<Vec<(f64, f64)>> = magnitudes.iter().map(|(_, v)| cdf(v)).collect();
    let largest = curves.iter().flatten().map(|p| p.0).fold(floor, f64::max);
    let mut chart = panel(
        area,
        path,
        caption,
        (0.0..largest * 1.05, 0.0..1.0),
        [x_desc, y_desc],
        60,
    )?;
    for (i, ((label, _), points)) in magnitudes.iter().zip(&curves).enumerate() {
        let color = COLORS[(i + 1) % COLORS.len()];
        chart
            .draw_series(LineSeries::new(points.iter().copied(), color.stroke_width(2)))
            .map_err(|e| draw(&e))?
            .label(label.clone())
            .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 18, y)], color.stroke_width(2)));
    }
    legend(&mut chart, path, Some(SeriesLabelPosition::LowerRight))
}

/// An error figure: (left) each series' errors over time as dots, (right) the distribution
/// (CDF) of their magnitudes; `unit` names the error (e.g. "along-track error (m)").
///
/// # Errors
/// No font for labels, or the image cannot be written.
pub fn error_figure(path: &Path, title: &str, unit: &str, series: &[Series]) -> Result<()> {
    register_font()?;
    let root = BitMapBackend::new(path, (1400, 560)).into_drawing_area();
    let draw = draw_err(path);
    root.fill(&WHITE).map_err(|e| draw(&e))?;
    let root = root.titled(title, ("sans-serif", 22)).map_err(|e| draw(&e))?;
    let (left, right) = root.split_horizontally(700);
    let (t0, t1, e0, e1) = bounds(&series.iter().collect::<Vec<_>>());
    let axes = (t0..t1, e0.min(0.0)..e1.max(0.0));
    let mut chart = panel(&left, path, "over time", axes, ["time (s)", unit], 60)?;
    for (i, s) in series.iter().enumerate() {
        let color = COLORS[(i + 1) % COLORS.len()];
        chart
            .draw_series(s.points.iter().map(|&p| Circle::new(p, 2, color.mix(0.7).filled())))
            .map_err(|e| draw(&e))?
            .label(s.label.clone())
            .legend(move |(x, y)| Circle::new((x + 9, y), 3, color.filled()));
    }
    legend(&mut chart, path, None)?;
    let magnitudes: Vec<(String, Vec<f64>)> = series
        .iter()
        .map(|s| (s.label.clone(), s.points.iter().map(|p| p.1).collect()))
        .collect();
    cdf_panel(
        &right,
        path,
        ["magnitude, CDF", &format!("|{unit}|"), "fraction"],
        &magnitudes,
        1e-6,
    )?;
    root.present()
        .with_context(|| format!("{}: cannot write", path.display()))?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cdf_sorts_magnitudes_and_ends_at_one() {
        let c = cdf(&[-0.3, 0.1, f64::NAN, 0.2]);
        assert_eq!(c.len(), 3);
        assert_eq!(c[0], (0.1, 1.0 / 3.0));
        assert_eq!(c[2].0, 0.3);
        assert!((c[2].1 - 1.0).abs() < 1e-12);
    }
}

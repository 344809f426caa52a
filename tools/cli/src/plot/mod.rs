//! PNG plots for `gprflow eval --plot`: trajectories against the truth seen from above, and
//! the error over time.

use std::path::Path;

use anyhow::{Context, Result, anyhow};
use plotters::prelude::*;

/// Where Debian, Fedora and Arch put DejaVu Sans (Debian package `fonts-dejavu-core`).
const FONT_CANDIDATES: [&str; 4] = [
    "/usr/share/fonts/truetype/dejavu/DejaVuSans.ttf",
    "/usr/share/fonts/dejavu/DejaVuSans.ttf",
    "/usr/share/fonts/TTF/DejaVuSans.ttf",
    "/usr/share/fonts/dejavu-sans-fonts/DejaVuSans.ttf",
];

fn register_font() -> Result<()> {
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

fn bounds(series: &[&Series]) -> (f64, f64, f64, f64) {
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

const COLORS: [RGBColor; 5] = [
    RGBColor(0, 0, 0),
    RGBColor(214, 39, 40),
    RGBColor(31, 119, 180),
    RGBColor(44, 160, 44),
    RGBColor(148, 103, 189),
];

/// Hough lines to draw over the trajectories: true ones dashed grey, estimated ones red.
#[derive(Debug, Clone, Default)]
pub struct Lines {
    /// True lines (rho m, theta rad).
    pub truth: Vec<(f64, f64)>,
    /// Estimated lines.
    pub estimate: Vec<(f64, f64)>,
}

/// The part of the line x cos(theta) + y sin(theta) = rho inside a square.
fn clip(rho: f64, theta: f64, (x0, x1, y0, y1): (f64, f64, f64, f64)) -> Option<[(f64, f64); 2]> {
    let (c, s) = (theta.cos(), theta.sin());
    let mut pts = Vec::new();
    if s.abs() > 1e-9 {
        for x in [x0, x1] {
            let y = (rho - x * c) / s;
            if (y0..=y1).contains(&y) {
                pts.push((x, y));
            }
        }
    }
    if c.abs() > 1e-9 {
        for y in [y0, y1] {
            let x = (rho - y * s) / c;
            if (x0..=x1).contains(&x) {
                pts.push((x, y));
            }
        }
    }
    (pts.len() >= 2).then(|| [pts[0], pts[pts.len() - 1]])
}

/// Draws `trajectories` (x, y in metres; the first is the truth) with `lines`, and
/// `errors` over time (seconds, metres), side by side into a PNG.
///
/// # Errors
/// No font for labels, or the image cannot be written.
pub fn trajectory_and_error(
    path: &Path,
    title: &str,
    trajectories: &[Series],
    lines: &Lines,
    errors: &[Series],
) -> Result<()> {
    register_font()?;
    let root = BitMapBackend::new(path, (1400, 640)).into_drawing_area();
    let draw = |e: &dyn std::fmt::Display| anyhow!("{}: {e}", path.display());
    root.fill(&WHITE).map_err(|e| draw(&e))?;
    let root = root.titled(title, ("sans-serif", 22)).map_err(|e| draw(&e))?;
    let (left, right) = root.split_horizontally(640);

    // from above, equal scales
    let (x0, x1, y0, y1) = bounds(&trajectories.iter().collect::<Vec<_>>());
    let span = (x1 - x0).max(y1 - y0);
    let (cx, cy) = (0.5 * (x0 + x1), 0.5 * (y0 + y1));
    let mut chart = ChartBuilder::on(&left)
        .margin(12)
        .caption("trajectory (m)", ("sans-serif", 18))
        .x_label_area_size(36)
        .y_label_area_size(52)
        .build_cartesian_2d(cx - span / 2.0..cx + span / 2.0, cy - span / 2.0..cy + span / 2.0)
        .map_err(|e| draw(&e))?;
    chart
        .configure_mesh()
        .x_desc("x (m)")
        .y_desc("y (m)")
        .draw()
        .map_err(|e| draw(&e))?;
    let square = (cx - span / 2.0, cx + span / 2.0, cy - span / 2.0, cy + span / 2.0);
    for (set, color, label) in [
        (&lines.truth, RGBColor(150, 150, 150), "true lines"),
        (&lines.estimate, RGBColor(214, 39, 40), "estimated lines"),
    ] {
        let segments: Vec<[(f64, f64); 2]> = set.iter().filter_map(|&(r, t)| clip(r, t, square)).collect();
        if segments.is_empty() {
            continue;
        }
        chart
            .draw_series(
                segments
                    .into_iter()
                    .map(|seg| PathElement::new(seg.to_vec(), color.stroke_width(1))),
            )
            .map_err(|e| draw(&e))?
            .label(label)
            .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 18, y)], color.stroke_width(1)));
    }
    for (i, s) in trajectories.iter().enumerate() {
        let color = COLORS[i % COLORS.len()];
        chart
            .draw_series(LineSeries::new(s.points.iter().copied(), color.stroke_width(2)))
            .map_err(|e| draw(&e))?
            .label(s.label.clone())
            .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 18, y)], color.stroke_width(2)));
    }
    chart
        .configure_series_labels()
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .draw()
        .map_err(|e| draw(&e))?;

    let (t0, t1, e0, e1) = bounds(&errors.iter().collect::<Vec<_>>());
    let mut chart = ChartBuilder::on(&right)
        .margin(12)
        .caption("error over time", ("sans-serif", 18))
        .x_label_area_size(36)
        .y_label_area_size(60)
        .build_cartesian_2d(t0..t1, e0.min(0.0)..e1)
        .map_err(|e| draw(&e))?;
    chart
        .configure_mesh()
        .x_desc("time (s)")
        .y_desc("error (m)")
        .draw()
        .map_err(|e| draw(&e))?;
    for (i, s) in errors.iter().enumerate() {
        let color = COLORS[(i + 1) % COLORS.len()];
        chart
            .draw_series(LineSeries::new(s.points.iter().copied(), color.stroke_width(2)))
            .map_err(|e| draw(&e))?
            .label(s.label.clone())
            .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 18, y)], color.stroke_width(2)));
    }
    chart
        .configure_series_labels()
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .draw()
        .map_err(|e| draw(&e))?;
    root.present()
        .with_context(|| format!("{}: cannot write", path.display()))?;
    Ok(())
}

/// A detected feature drawn over a radargram, in image coordinates (column, sample).
#[derive(Debug, Clone)]
pub struct Feature {
    /// The apex.
    pub apex: (f64, f64),
    /// The fitted hyperbola (empty when unknown).
    pub curve: Vec<(f64, f64)>,
    /// Text next to the apex (line id).
    pub label: String,
}

/// Renders traces (one column each, samples down) as a grey-scale radargram: the mean
/// trace is removed (horizontal banding), a gain growing linearly with depth applied and
/// the 99th percentile of magnitudes mapped to full scale; each value a square of
/// `pixels_per_value` pixels. `features` are drawn on top: the hyperbola in red, the apex as a cross, the
/// label beside it.
///
/// # Errors
/// No traces, or the image cannot be written.
pub fn radargram(path: &Path, traces: &[Vec<f32>], features: &[Feature], pixels_per_value: u32) -> Result<()> {
    let block = pixels_per_value.max(1);
    let width = traces.len();
    let height = traces.iter().map(Vec::len).max().unwrap_or(0);
    if width == 0 || height == 0 {
        anyhow::bail!("no traces to draw");
    }
    let mut mean = vec![0.0f64; height];
    for t in traces {
        for (m, v) in mean.iter_mut().zip(t) {
            *m += f64::from(*v) / width as f64;
        }
    }
    let gain = |k: usize| 1.0 + 7.0 * k as f64 / height as f64;
    let value = |t: &Vec<f32>, k: usize| t.get(k).map_or(0.0, |v| (f64::from(*v) - mean[k]) * gain(k));
    let mut magnitudes: Vec<f64> = traces
        .iter()
        .flat_map(|t| (0..height).map(move |k| value(t, k).abs()))
        .collect();
    let at = ((magnitudes.len() as f64 * 0.99) as usize).min(magnitudes.len() - 1);
    let full_scale = *magnitudes.select_nth_unstable_by(at, f64::total_cmp).1;
    let full_scale = if full_scale > 0.0 { full_scale } else { 1.0 };
    let root = BitMapBackend::new(path, (width as u32 * block, height as u32 * block)).into_drawing_area();
    let s = block as i32;
    for (x, t) in traces.iter().enumerate() {
        for k in 0..height {
            let g = (128.0 + 127.0 * (value(t, k) / full_scale).clamp(-1.0, 1.0)) as u8;
            for (dx, dy) in (0..s).flat_map(|dx| (0..s).map(move |dy| (dx, dy))) {
                root.draw_pixel((x as i32 * s + dx, k as i32 * s + dy), &RGBColor(g, g, g))
                    .map_err(|e| anyhow!("{}: {e}", path.display()))?;
            }
        }
    }
    if !features.is_empty() {
        register_font()?;
    }
    let err = |e: DrawingAreaErrorKind<_>| anyhow!("{}: {e}", path.display());
    // image coordinates to the centre of the value's pixel block
    let px = |(x, y): (f64, f64)| (((x + 0.5) * f64::from(s)) as i32, ((y + 0.5) * f64::from(s)) as i32);
    for f in features {
        if f.curve.len() > 1 {
            root.draw(&PathElement::new(
                f.curve.iter().copied().map(px).collect::<Vec<_>>(),
                RED.stroke_width(1),
            ))
            .map_err(err)?;
        }
        let (x, y) = px(f.apex);
        root.draw(&Cross::new((x, y), 4, YELLOW.stroke_width(2))).map_err(err)?;
        root.draw(&Text::new(
            f.label.clone(),
            (x + 6, y - 14),
            ("sans-serif", 13).into_font().color(&YELLOW),
        ))
        .map_err(err)?;
    }
    root.present()
        .with_context(|| format!("{}: cannot write", path.display()))?;
    Ok(())
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
    let draw = |e: &dyn std::fmt::Display| anyhow!("{}: {e}", path.display());
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
    chart
        .configure_series_labels()
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .draw()
        .map_err(|e| draw(&e))?;
    root.present()
        .with_context(|| format!("{}: cannot write", path.display()))?;
    Ok(())
}

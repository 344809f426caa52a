//! The figure of `gprflow eval --plot`: the runs against the truth from above, a zoom on the
//! largest error, the error over time and its distribution.

use std::path::Path;

use anyhow::{Context, Result};
use plotters::coord::Shift;
use plotters::prelude::*;

use super::{COLORS, Series, bounds, cdf_panel, draw_err, legend, panel, register_font};

/// Hough lines to draw over the trajectories: true ones grey, estimated ones red.
#[derive(Debug, Clone, Default)]
pub struct Lines {
    /// True lines (rho m, theta rad).
    pub truth: Vec<(f64, f64)>,
    /// Estimated lines.
    pub estimate: Vec<(f64, f64)>,
}

/// One evaluated run: its path from above and its error against the truth.
#[derive(Debug, Clone)]
pub struct RunTrack {
    /// Legend label.
    pub label: String,
    /// Positions (x, y), m, at the stamps paired with the truth.
    pub xy: Vec<(f64, f64)>,
    /// The truth's positions at the same stamps.
    pub truth_xy: Vec<(f64, f64)>,
    /// Seconds since the first paired stamp of the first run.
    pub seconds: Vec<f64>,
}

impl RunTrack {
    /// The distance from the truth at each paired stamp, m.
    fn errors(&self) -> Vec<f64> {
        self.xy
            .iter()
            .zip(&self.truth_xy)
            .map(|(e, t)| (e.0 - t.0).hypot(e.1 - t.1))
            .collect()
    }

    /// Index of the largest error.
    fn worst(&self) -> Option<usize> {
        self.errors()
            .iter()
            .enumerate()
            .max_by(|a, b| a.1.total_cmp(b.1))
            .map(|(i, _)| i)
    }
}

/// What [`trajectory_figure`] draws.
#[derive(Debug, Clone)]
pub struct TrajectoryFigure<'a> {
    /// Title over all panels.
    pub title: &'a str,
    /// The truth's whole path.
    pub truth: Series,
    /// The runs; the first is the one the zoom follows.
    pub runs: Vec<RunTrack>,
    /// More paths drawn from above only (other pose topics).
    pub extra: Vec<Series>,
    /// Along- and cross-track error of the first run over time (seconds, m).
    pub along_cross: Option<(Series, Series)>,
    /// Hough lines.
    pub lines: Lines,
}

/// The part of the line x cos(theta) + y sin(theta) = rho inside a rectangle.
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

/// Axis ranges for a view from above of `b` drawn into `w` x `h` pixels: equal scales unless
/// that would squash the picture to under a quarter of one side, in which case the shorter
/// extent is stretched and the factor returned.
pub(crate) fn plan_view(b: (f64, f64, f64, f64), w: u32, h: u32) -> ((f64, f64, f64, f64), f64) {
    let (dx, dy) = ((b.1 - b.0).max(1e-3), (b.3 - b.2).max(1e-3));
    let (cx, cy) = (0.5 * (b.0 + b.1), 0.5 * (b.2 + b.3));
    // metres per pixel that fit each extent
    let (sx, sy) = (dx / f64::from(w), dy / f64::from(h));
    let s = sx.max(sy);
    let (mut hx, mut hy) = (0.5 * s * f64::from(w), 0.5 * s * f64::from(h));
    let mut stretch = 1.0;
    if sx > 4.0 * sy {
        stretch = sx / (4.0 * sy);
        hy = 0.5 * dy * 1.1;
    } else if sy > 4.0 * sx {
        stretch = sy / (4.0 * sx);
        hx = 0.5 * dx * 1.1;
    }
    hx = hx.max(1e-3);
    hy = hy.max(1e-3);
    ((cx - hx, cx + hx, cy - hy, cy + hy), stretch)
}

/// Draws the paths of `fig` from above into `area`, inside `view`.
fn from_above(
    area: &DrawingArea<BitMapBackend<'_>, Shift>,
    path: &Path,
    caption: &str,
    fig: &TrajectoryFigure<'_>,
    view: (f64, f64, f64, f64),
    mark: Option<((f64, f64), (f64, f64))>,
) -> Result<()> {
    let draw = draw_err(path);
    let axes = (view.0..view.1, view.2..view.3);
    let mut chart = panel(area, path, caption, axes, ["x (m)", "y (m)"], 56)?;
    for (set, color, label) in [
        (&fig.lines.truth, RGBColor(150, 150, 150), "true lines"),
        (&fig.lines.estimate, RGBColor(214, 39, 40), "estimated lines"),
    ] {
        let segments: Vec<[(f64, f64); 2]> = set.iter().filter_map(|&(r, t)| clip(r, t, view)).collect();
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
    let inside = |p: &(f64, f64)| p.0.is_finite() && p.1.is_finite();
    // label, points, colour, line width
    type Drawn<'s> = (&'s str, &'s [(f64, f64)], RGBColor, u32);
    let mut series: Vec<Drawn<'_>> = vec![(&fig.truth.label, &fig.truth.points, BLACK, 3)];
    for (i, r) in fig.runs.iter().enumerate() {
        series.push((&r.label, &r.xy, COLORS[(i + 1) % COLORS.len()], 2));
    }
    for (i, s) in fig.extra.iter().enumerate() {
        series.push((&s.label, &s.points, COLORS[(fig.runs.len() + i + 1) % COLORS.len()], 1));
    }
    for (label, points, color, width) in series {
        chart
            .draw_series(LineSeries::new(
                points.iter().copied().filter(inside),
                color.stroke_width(width),
            ))
            .map_err(|e| draw(&e))?
            .label(label.to_owned())
            .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 18, y)], color.stroke_width(width)));
    }
    if let Some((estimate, truth)) = mark {
        let color = COLORS[1];
        chart
            .draw_series([PathElement::new(vec![estimate, truth], color.stroke_width(2))])
            .map_err(|e| draw(&e))?;
        chart
            .draw_series([
                Circle::new(estimate, 5, color.filled()),
                Circle::new(truth, 5, BLACK.filled()),
            ])
            .map_err(|e| draw(&e))?;
    }
    legend(&mut chart, path, Some(SeriesLabelPosition::UpperRight))?;
    Ok(())
}

/// Draws `fig` into a PNG: (top left) the truth and the runs from above, on equal scales
/// unless the course is long and thin; (top right) a zoom on the first run's largest error,
/// on equal scales, the estimate and the truth at that moment joined; (bottom left) each
/// run's distance from the truth over time, with the first run's along- and cross-track
/// error; (bottom right) the distribution (CDF) of each run's distance from the truth.
///
/// # Errors
/// No font for labels, nothing to draw, or the image cannot be written.
pub fn trajectory_figure(path: &Path, fig: &TrajectoryFigure<'_>) -> Result<()> {
    register_font()?;
    let first = fig.runs.first().context("no run to draw")?;
    let (w, h) = (1600u32, 1100u32);
    let root = BitMapBackend::new(path, (w, h)).into_drawing_area();
    let draw = draw_err(path);
    root.fill(&WHITE).map_err(|e| draw(&e))?;
    let root = root.titled(fig.title, ("sans-serif", 22)).map_err(|e| draw(&e))?;
    let (top, bottom) = root.split_vertically(600);
    let (top_left, top_right) = top.split_horizontally(w / 2);
    let (bottom_left, bottom_right) = bottom.split_horizontally(w / 2);

    // from above: every path
    let mut all: Vec<&Series> = vec![&fig.truth];
    all.extend(&fig.extra);
    let run_series: Vec<Series> = fig
        .runs
        .iter()
        .map(|r| Series {
            label: r.label.clone(),
            points: r.xy.clone(),
        })
        .collect();
    all.extend(&run_series);
    let (view, stretch) = plan_view(bounds(&all), w / 2 - 80, 600 - 90);
    let caption = if stretch > 1.01 {
        format!("from above (m; the short side stretched {stretch:.1}x)")
    } else {
        "from above (m)".to_owned()
    };
    from_above(&top_left, path, &caption, fig, view, None)?;

    // the zoom: equal scales around the largest error of the first run
    let worst = first
        .worst()
        .context("the first run has no poses paired with the truth")?;
    let (e, t) = (first.xy[worst], first.truth_xy[worst]);
    let error = (e.0 - t.0).hypot(e.1 - t.1);
    let half = (2.5 * error).max(0.25);
    let (cx, cy) = (0.5 * (e.0 + t.0), 0.5 * (e.1 + t.1));
    let aspect = f64::from(w / 2 - 80) / f64::from(600 - 90);
    let zoom = (cx - half * aspect, cx + half * aspect, cy - half, cy + half);
    let seconds = first.seconds.get(worst).copied().unwrap_or(0.0);
    from_above(
        &top_right,
        path,
        &format!(
            "zoom on the largest error of {}: {error:.3} m at {seconds:.1} s",
            first.label
        ),
        fig,
        zoom,
        Some((e, t)),
    )?;

    // error over time
    let mut over_time: Vec<(Series, RGBColor, u32)> = fig
        .runs
        .iter()
        .enumerate()
        .map(|(i, r)| {
            (
                Series {
                    label: format!("{} distance from truth", r.label),
                    points: r.seconds.iter().copied().zip(r.errors()).collect(),
                },
                COLORS[(i + 1) % COLORS.len()],
                2,
            )
        })
        .collect();
    if let Some((along, cross)) = &fig.along_cross {
        over_time.push((along.clone(), RGBColor(255, 127, 14), 1));
        over_time.push((cross.clone(), RGBColor(23, 190, 207), 1));
    }
    let refs: Vec<&Series> = over_time.iter().map(|(s, _, _)| s).collect();
    let (t0, t1, e0, e1) = bounds(&refs);
    let axes = (t0..t1, e0.min(0.0)..e1);
    let mut chart = panel(
        &bottom_left,
        path,
        "error over time",
        axes,
        ["time (s)", "error (m)"],
        60,
    )?;
    for (s, color, width) in &over_time {
        let (color, width) = (*color, *width);
        chart
            .draw_series(LineSeries::new(s.points.iter().copied(), color.stroke_width(width)))
            .map_err(|e| draw(&e))?
            .label(s.label.clone())
            .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 18, y)], color.stroke_width(width)));
    }
    legend(&mut chart, path, Some(SeriesLabelPosition::UpperLeft))?;

    // distribution
    let errors: Vec<(String, Vec<f64>)> = fig.runs.iter().map(|r| (r.label.clone(), r.errors())).collect();
    cdf_panel(
        &bottom_right,
        path,
        [
            "distance from the truth, CDF",
            "distance from the truth (m)",
            "fraction of poses",
        ],
        &errors,
        1e-3,
    )?;
    root.present()
        .with_context(|| format!("{}: cannot write", path.display()))?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn plan_view_keeps_equal_scales_for_a_compact_course() {
        let ((x0, x1, y0, y1), stretch) = plan_view((0.0, 10.0, 0.0, 8.0), 700, 500);
        assert_eq!(stretch, 1.0);
        let (mx, my) = ((x1 - x0) / 700.0, (y1 - y0) / 500.0);
        assert!((mx - my).abs() < 1e-12, "{mx} vs {my}");
        assert!(x0 <= 0.0 && x1 >= 10.0 && y0 <= 0.0 && y1 >= 8.0);
    }

    #[test]
    fn plan_view_stretches_a_long_thin_course() {
        // an 8 m line with 5 cm of wander
        let ((x0, x1, y0, y1), stretch) = plan_view((0.0, 8.0, -0.025, 0.025), 700, 500);
        assert!(stretch > 10.0, "{stretch}");
        assert!(x0 <= 0.0 && x1 >= 8.0 && y0 <= -0.025 && y1 >= 0.025);
        // the thin side fills most of its pixels
        assert!((y1 - y0) < 0.06, "{y0}..{y1}");
    }

    #[test]
    fn clip_finds_the_chord_of_a_diagonal() {
        let [a, b] = clip(
            0.0,
            std::f64::consts::FRAC_PI_4 + std::f64::consts::FRAC_PI_2,
            (-1.0, 1.0, -1.0, 1.0),
        )
        .expect("crosses");
        assert!((a.0 - a.1).abs() < 1e-9 && (b.0 - b.1).abs() < 1e-9);
    }
}

//! Radargram pictures: traces as columns with distance and two-way-time axes, an optional
//! depth axis, a colour scale, and detected features on top.

use std::path::Path;

use anyhow::{Context, Result};
use plotters::prelude::*;

use super::{draw_err, register_font};

/// A detected feature drawn over a radargram, in data coordinates (column, sample).
#[derive(Debug, Clone)]
pub struct Feature {
    /// The apex.
    pub apex: (f64, f64),
    /// The fitted hyperbola (empty when unknown).
    pub curve: Vec<(f64, f64)>,
    /// Text next to the apex (line id).
    pub label: String,
}

/// Colour map.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum Colormap {
    /// Black (negative) to white (positive).
    Grey,
    /// Blue (negative) through white to red (positive).
    Seismic,
}

/// What [`radargram`] draws.
#[derive(Debug, Clone)]
pub struct Radargram<'a> {
    /// Title over the picture.
    pub title: &'a str,
    /// One column per trace, samples down.
    pub traces: &'a [Vec<f32>],
    /// Along-track distance of each trace, m, when known and increasing; else the axis counts
    /// traces.
    pub distances_m: Option<Vec<f64>>,
    /// Sample interval, ns (`None`: the axis counts samples).
    pub sample_interval_ns: Option<f64>,
    /// Wave speed in the ground, m/ns, for a depth axis (depth = v t / 2).
    pub velocity_m_per_ns: Option<f64>,
    /// Remove the mean trace (horizontal banding: the direct wave, ringing).
    pub remove_background: bool,
    /// Gain with depth.
    pub gain: gprflow_viz::Gain,
    /// Percentile of magnitudes mapped to the ends of the colour scale (0-100].
    pub clip_percentile: f64,
    /// Colour map.
    pub colormap: Colormap,
    /// Features on top.
    pub features: &'a [Feature],
}

/// Picture size, pixels.
const WIDTH: u32 = 1400;
const HEIGHT: u32 = 820;
/// The colour bar's strip on the right, pixels.
const BAR: u32 = 120;

impl Radargram<'_> {
    /// The values drawn, column-major (`cols` x `rows`), and the value mapped to the end of
    /// the colour scale.
    fn processed(&self) -> Result<(Vec<Vec<f64>>, f64)> {
        let how = gprflow_viz::Rendering {
            remove_background: self.remove_background,
            gain: self.gain,
            clip_percentile: self.clip_percentile,
        };
        Ok(gprflow_viz::amplitudes(self.traces, &how)?)
    }

    /// The along-track position of (fractional) column `c`: its distance, or `c` itself.
    fn x_of(&self, c: f64) -> f64 {
        match &self.distances_m {
            Some(d) if d.len() > 1 => {
                let i = (c.floor().max(0.0) as usize).min(d.len() - 2);
                let f = c - i as f64;
                d[i] + f * (d[i + 1] - d[i])
            }
            _ => c,
        }
    }

    /// The column at along-track position `x`.
    fn column_at(&self, x: f64) -> usize {
        let cols = self.traces.len();
        match &self.distances_m {
            Some(d) if d.len() > 1 => d.partition_point(|&v| v < x).min(cols - 1),
            _ => (x.round().max(0.0) as usize).min(cols - 1),
        }
    }

    /// Two-way time (or sample number) of (fractional) sample `k`.
    fn t_of(&self, k: f64) -> f64 {
        k * self.sample_interval_ns.unwrap_or(1.0)
    }
}

/// `value` in [-1, 1] as a colour.
fn colour(map: Colormap, value: f64) -> RGBColor {
    let v = value.clamp(-1.0, 1.0);
    match map {
        Colormap::Grey => {
            let g = (127.5 + 127.5 * v) as u8;
            RGBColor(g, g, g)
        }
        Colormap::Seismic => {
            // white at zero, saturated blue / red at the ends
            let fade = |a: f64| (255.0 * (1.0 - a)) as u8;
            if v >= 0.0 {
                RGBColor(255 - (75.0 * (v - 0.5).max(0.0) * 2.0) as u8, fade(v), fade(v))
            } else {
                RGBColor(fade(-v), fade(-v), 255 - (75.0 * (-v - 0.5).max(0.0) * 2.0) as u8)
            }
        }
    }
}

/// Checks that `distances` can serve as the along-track axis: finite, strictly increasing
/// overall and never going back.
#[must_use]
pub fn usable_distances(distances: &[f64]) -> bool {
    distances.len() > 1
        && distances.iter().all(|d| d.is_finite())
        && distances.windows(2).all(|w| w[1] >= w[0])
        && distances[distances.len() - 1] > distances[0]
}

/// Draws `r` into a PNG of 1400 x 820 pixels whatever the trace count (columns averaged
/// into pixels, or stretched): along-track distance (or trace number) across, two-way time
/// (or sample number) down, depth on the right when a velocity is given, the colour scale
/// beside it, features on top (the hyperbola red, the apex a yellow cross, the label).
///
/// # Errors
/// No traces, a bad clip percentile, no font, or the image cannot be written.
pub fn radargram(path: &Path, r: &Radargram<'_>) -> Result<()> {
    register_font()?;
    let (values, full_scale) = r.processed()?;
    let (cols, rows) = (values.len(), values[0].len());
    let err = draw_err(path);
    let root = BitMapBackend::new(path, (WIDTH, HEIGHT)).into_drawing_area();
    root.fill(&WHITE).map_err(|e| err(&e))?;
    let root = root.titled(r.title, ("sans-serif", 20)).map_err(|e| err(&e))?;
    let (main, bar) = root.split_horizontally(WIDTH - BAR);

    let (x0, x1) = (r.x_of(0.0), r.x_of((cols - 1) as f64).max(r.x_of(0.0) + 1e-9));
    let t1 = r.t_of((rows - 1) as f64).max(1e-9);
    let x_desc = if r.distances_m.is_some() {
        "distance (m)"
    } else {
        "trace"
    };
    let t_desc = if r.sample_interval_ns.is_some() {
        "two-way time (ns)"
    } else {
        "sample"
    };
    let mut builder = ChartBuilder::on(&main);
    builder.margin(10).x_label_area_size(40).y_label_area_size(64);
    if r.velocity_m_per_ns.is_some() {
        builder.right_y_label_area_size(64);
    }
    // time grows downwards: the axis runs over -t and labels |t|
    let mut chart = builder
        .build_cartesian_2d(x0..x1, -t1..0.0)
        .map_err(|e| err(&e))?
        .set_secondary_coord(x0..x1, -(r.velocity_m_per_ns.unwrap_or(1.0) * t1 / 2.0)..0.0);

    // the raster, one value per pixel of the plotting area
    let area = chart.plotting_area();
    let (px, py) = area.get_pixel_range();
    let (w, h) = ((px.end - px.start).max(1) as usize, (py.end - py.start).max(1) as usize);
    let mut pixels = Vec::with_capacity(w);
    for i in 0..w {
        // the columns under this pixel, averaged
        let xa = x0 + (x1 - x0) * i as f64 / w as f64;
        let xb = x0 + (x1 - x0) * (i + 1) as f64 / w as f64;
        let (ca, cb) = (r.column_at(xa), r.column_at(xb).max(r.column_at(xa) + 1).min(cols));
        let column: Vec<f64> = (0..h)
            .map(|j| {
                let k = ((j as f64 + 0.5) / h as f64 * rows as f64) as usize;
                let k = k.min(rows - 1);
                values[ca..cb].iter().map(|c| c[k]).sum::<f64>() / (cb - ca) as f64
            })
            .collect();
        pixels.push(column);
    }
    let base = area.strip_coord_spec();
    for (i, column) in pixels.iter().enumerate() {
        for (j, v) in column.iter().enumerate() {
            base.draw_pixel((i as i32, j as i32), &colour(r.colormap, v / full_scale))
                .map_err(|e| err(&e))?;
        }
    }
    chart
        .configure_mesh()
        .disable_mesh()
        .x_desc(x_desc)
        .y_desc(t_desc)
        .y_label_formatter(&|v| format!("{:.0}", v.abs()))
        .draw()
        .map_err(|e| err(&e))?;
    if let Some(v) = r.velocity_m_per_ns {
        chart
            .configure_secondary_axes()
            .y_desc(format!("depth (m) at {v} m/ns"))
            .y_label_formatter(&|d| format!("{:.2}", d.abs()))
            .draw()
            .map_err(|e| err(&e))?;
    }
    let at = |(c, k): (f64, f64)| (r.x_of(c), -r.t_of(k));
    for f in r.features {
        if f.curve.len() > 1 {
            chart
                .draw_series(std::iter::once(PathElement::new(
                    f.curve.iter().copied().map(at).collect::<Vec<_>>(),
                    RED.stroke_width(2),
                )))
                .map_err(|e| err(&e))?;
        }
        let apex = at(f.apex);
        chart
            .draw_series(std::iter::once(
                EmptyElement::at(apex)
                    + Cross::new((0, 0), 5, YELLOW.stroke_width(2))
                    + Text::new(f.label.clone(), (7, -16), ("sans-serif", 14).into_font().color(&YELLOW)),
            ))
            .map_err(|e| err(&e))?;
    }

    // the colour scale
    let mut scale = ChartBuilder::on(&bar)
        .margin_top(40)
        .margin_bottom(50)
        .margin_right(58)
        .y_label_area_size(0)
        .right_y_label_area_size(0)
        .build_cartesian_2d(0.0..1.0, -full_scale..full_scale)
        .map_err(|e| err(&e))?;
    let steps = 200;
    scale
        .draw_series((0..steps).map(|s| {
            let a = -full_scale + 2.0 * full_scale * s as f64 / steps as f64;
            let b = a + 2.0 * full_scale / steps as f64;
            Rectangle::new(
                [(0.0, a), (1.0, b)],
                colour(r.colormap, (a + b) / (2.0 * full_scale)).filled(),
            )
        }))
        .map_err(|e| err(&e))?;
    let label = |v: f64| format!("{v:.3e}");
    let (_, by) = scale.plotting_area().get_pixel_range();
    let style = ("sans-serif", 12).into_font().color(&BLACK);
    let right = scale.plotting_area().get_pixel_range().0.end + 4;
    for (text, y) in [
        (format!("+{}", label(full_scale)), by.start),
        ("0".to_owned(), (by.start + by.end) / 2),
        (label(-full_scale), by.end - 12),
    ] {
        root.draw(&Text::new(text, (right, y), style.clone()))
            .map_err(|e| err(&e))?;
    }
    let gain = match r.gain {
        gprflow_viz::Gain::None => "no gain",
        gprflow_viz::Gain::Linear => "linear gain",
        gprflow_viz::Gain::Agc => "AGC",
    };
    root.draw(&Text::new(
        format!("{gain}, P{}", r.clip_percentile),
        (WIDTH as i32 - BAR as i32 + 4, HEIGHT as i32 - 44),
        ("sans-serif", 12).into_font().color(&BLACK),
    ))
    .map_err(|e| err(&e))?;
    root.present()
        .with_context(|| format!("{}: cannot write", path.display()))?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn picture(traces: &[Vec<f32>]) -> Radargram<'_> {
        Radargram {
            title: "t",
            traces,
            distances_m: None,
            sample_interval_ns: Some(0.5),
            velocity_m_per_ns: None,
            remove_background: true,
            gain: gprflow_viz::Gain::None,
            clip_percentile: 100.0,
            colormap: Colormap::Grey,
            features: &[],
        }
    }

    #[test]
    fn distance_axis_maps_columns_both_ways() {
        let traces = vec![vec![0.0f32]; 3];
        let mut r = picture(&traces);
        r.distances_m = Some(vec![1.0, 1.5, 3.0]);
        assert!((r.x_of(1.5) - 2.25).abs() < 1e-12);
        assert_eq!(r.column_at(1.2), 1);
        assert_eq!(r.column_at(9.0), 2);
        assert!(usable_distances(&[0.0, 0.0, 0.1]));
        assert!(!usable_distances(&[0.0, f64::NAN]));
        assert!(!usable_distances(&[0.0, 0.2, 0.1]));
    }

    #[test]
    fn seismic_is_white_at_zero_and_saturated_at_the_ends() {
        assert_eq!(colour(Colormap::Seismic, 0.0), RGBColor(255, 255, 255));
        assert_eq!(colour(Colormap::Seismic, 1.0), RGBColor(180, 0, 0));
        assert_eq!(colour(Colormap::Seismic, -1.0), RGBColor(0, 0, 180));
        assert_eq!(colour(Colormap::Grey, -1.0), RGBColor(0, 0, 0));
    }
}

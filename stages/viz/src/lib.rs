//! Pictures of GPR data for people: [`amplitudes`] turns traces into the values a radargram
//! shows (background removed, gained with depth, clipped at a percentile), and the `viz`
//! stage ([`VizStage`]) publishes what Foxglove displays out of the box: a rolling radargram
//! and every submap as `sensor_msgs/Image`, the estimated trajectory as `nav_msgs/Path` and
//! each state's pose as `geometry_msgs/PoseStamped`.

mod node;

pub use node::{VizParams, VizStage};

/// Amplitude gain with two-way time.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Deserialize, schemars::JsonSchema)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
#[serde(rename_all = "snake_case")]
pub enum Gain {
    /// None: the amplitudes as recorded (after background removal).
    None,
    /// Growing linearly from 1 at the first sample to 8 at the last.
    #[default]
    Linear,
    /// Automatic gain control: each value divided by the RMS of its trace over a window of
    /// 1/8 of the trace.
    Agc,
}

/// How traces become picture values.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Rendering {
    /// Subtract the mean trace (horizontal banding: the direct wave, ringing).
    pub remove_background: bool,
    /// Gain with depth.
    pub gain: Gain,
    /// Percentile of magnitudes that maps to the ends of the scale, (0, 100].
    pub clip_percentile: f64,
}

/// Why traces cannot be drawn.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum RenderError {
    /// No traces, or only empty ones.
    Empty,
    /// The clip percentile is outside (0, 100].
    Clip(String),
}

impl std::fmt::Display for RenderError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Empty => write!(f, "no traces to draw"),
            Self::Clip(p) => write!(f, "clip percentile {p} is not in (0, 100]"),
        }
    }
}

impl std::error::Error for RenderError {}

/// The values a radargram of `traces` (one column each, samples down; shorter ones padded
/// with zeros, non-finite values drawn as zero) shows, column-major, and the magnitude that
/// maps to the ends of the scale (the `clip_percentile` of all magnitudes; 1 when they are
/// all zero).
///
/// # Errors
/// No samples, or a clip percentile outside (0, 100].
pub fn amplitudes<T: AsRef<[f32]>>(traces: &[T], how: &Rendering) -> Result<(Vec<Vec<f64>>, f64), RenderError> {
    let cols = traces.len();
    let rows = traces.iter().map(|t| t.as_ref().len()).max().unwrap_or(0);
    if cols == 0 || rows == 0 {
        return Err(RenderError::Empty);
    }
    if !(how.clip_percentile > 0.0 && how.clip_percentile <= 100.0) {
        return Err(RenderError::Clip(how.clip_percentile.to_string()));
    }
    let finite = |v: f32| if v.is_finite() { f64::from(v) } else { 0.0 };
    let mut mean = vec![0.0f64; rows];
    if how.remove_background {
        for t in traces {
            for (m, v) in mean.iter_mut().zip(t.as_ref()) {
                *m += finite(*v) / cols as f64;
            }
        }
    }
    let mut values: Vec<Vec<f64>> = traces
        .iter()
        .map(|t| {
            let t = t.as_ref();
            (0..rows)
                .map(|k| t.get(k).map_or(0.0, |v| finite(*v)) - mean[k])
                .collect()
        })
        .collect();
    match how.gain {
        Gain::None => {}
        Gain::Linear => {
            for column in &mut values {
                for (k, v) in column.iter_mut().enumerate() {
                    *v *= 1.0 + 7.0 * k as f64 / rows as f64;
                }
            }
        }
        Gain::Agc => {
            let half = (rows / 16).max(1);
            for column in &mut values {
                let mut squares = Vec::with_capacity(rows + 1);
                squares.push(0.0);
                for v in column.iter() {
                    squares.push(squares[squares.len() - 1] + v * v);
                }
                let scaled: Vec<f64> = (0..rows)
                    .map(|k| {
                        let (a, b) = (k.saturating_sub(half), (k + half + 1).min(rows));
                        let rms = ((squares[b] - squares[a]) / (b - a) as f64).sqrt();
                        if rms > 0.0 { column[k] / rms } else { 0.0 }
                    })
                    .collect();
                *column = scaled;
            }
        }
    }
    let mut magnitudes: Vec<f64> = values.iter().flatten().map(|v| v.abs()).collect();
    let at = ((magnitudes.len() as f64 * how.clip_percentile / 100.0) as usize).min(magnitudes.len() - 1);
    let full_scale = *magnitudes.select_nth_unstable_by(at, f64::total_cmp).1;
    Ok((values, if full_scale > 0.0 { full_scale } else { 1.0 }))
}

/// `values` (column-major, as [`amplitudes`] gives them) as an 8-bit grey image, row-major:
/// 0 at `-full_scale` and below, 255 at `+full_scale` and above.
#[must_use]
pub fn mono8(values: &[Vec<f64>], full_scale: f64) -> Vec<u8> {
    let rows = values.first().map_or(0, Vec::len);
    let mut out = Vec::with_capacity(rows * values.len());
    for k in 0..rows {
        for column in values {
            out.push((127.5 + 127.5 * (column[k] / full_scale).clamp(-1.0, 1.0)) as u8);
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    const PLAIN: Rendering = Rendering {
        remove_background: true,
        gain: Gain::None,
        clip_percentile: 100.0,
    };

    #[test]
    fn background_removal_leaves_only_what_varies_along_track() {
        let traces: Vec<Vec<f32>> = (0..4).map(|i| vec![5.0, 5.0 + i as f32]).collect();
        let (v, full) = amplitudes(&traces, &PLAIN).expect("values");
        assert!(v.iter().all(|c| c[0] == 0.0));
        assert!((v[3][1] - 1.5).abs() < 1e-12 && (v[0][1] + 1.5).abs() < 1e-12);
        assert!((full - 1.5).abs() < 1e-12);
    }

    #[test]
    fn agc_evens_out_amplitude_with_depth() {
        // a weak deep half: AGC brings both halves to unit RMS
        let trace: Vec<f32> = (0..64)
            .map(|k| if k < 32 { 10.0 } else { 0.1 } * if k % 2 == 0 { 1.0 } else { -1.0 })
            .collect();
        let how = Rendering {
            remove_background: false,
            gain: Gain::Agc,
            ..PLAIN
        };
        let (v, _) = amplitudes(&[trace], &how).expect("values");
        assert!((v[0][8].abs() - 1.0).abs() < 1e-9 && (v[0][56].abs() - 1.0).abs() < 1e-9);
    }

    #[test]
    fn linear_gain_grows_to_eight_times() {
        let how = Rendering {
            remove_background: false,
            gain: Gain::Linear,
            ..PLAIN
        };
        let (v, _) = amplitudes(&[vec![1.0f32; 100]], &how).expect("values");
        assert!((v[0][0] - 1.0).abs() < 1e-12 && (v[0][99] - 7.93).abs() < 1e-9);
    }

    #[test]
    fn bad_clip_empty_input_and_nan_are_handled() {
        let traces = vec![vec![1.0f32, f32::NAN]];
        let how = Rendering {
            clip_percentile: 0.0,
            ..PLAIN
        };
        assert!(matches!(amplitudes(&traces, &how), Err(RenderError::Clip(_))));
        assert_eq!(amplitudes::<Vec<f32>>(&[], &PLAIN), Err(RenderError::Empty));
        let (v, _) = amplitudes(&traces, &PLAIN).expect("values");
        assert!(v[0].iter().all(|x| x.is_finite()));
    }

    #[test]
    fn mono8_is_row_major_and_clipped() {
        let values = vec![vec![-2.0, 0.0], vec![1.0, 0.5]];
        assert_eq!(mono8(&values, 1.0), vec![0, 255, 127, 191]);
    }
}

//! `gprflow radargram`: a recording's traces or submaps, or a radar file, drawn as a picture.

use std::io::Write as _;
use std::path::Path;
use std::process::ExitCode;

use anyhow::{Context, Result, bail};
use gprflow::record::Recording;

use crate::eval::topic_name;

/// What `gprflow radargram` draws.
#[derive(Debug, Clone)]
pub struct RadargramRequest<'a> {
    /// Recording or radar file.
    pub input: &'a Path,
    /// Trace, sweep or submap topic.
    pub topic: &'a str,
    /// Seconds after the first trace: from, to.
    pub window_s: (f64, Option<f64>),
    /// Submap topics: the id to draw (default the most salient).
    pub submap: Option<u32>,
    /// Line observations to draw over it: a topic, or `None` for the recording's first
    /// `LineObservation` topic if any.
    pub features: Option<&'a str>,
    /// Draw no features.
    pub no_features: bool,
    /// Wave speed in the ground for a depth axis, m/ns.
    pub velocity_m_per_ns: Option<f64>,
    /// Gain with depth.
    pub gain: gprflow_viz::Gain,
    /// Percentile of magnitudes at the ends of the colour scale.
    pub clip_percentile: f64,
    /// Colour map.
    pub colormap: crate::plot::Colormap,
    /// Keep the mean trace (no background removal).
    pub keep_background: bool,
    /// PNG to write.
    pub output: &'a Path,
}

/// Where a submap lies along track, for placing features on it.
#[derive(Debug, Clone, Copy)]
struct SubmapFrame {
    start_distance_m: f64,
    end_distance_m: f64,
    resolution_m: f64,
    sample_interval_ns: f64,
    cols: usize,
    rows: usize,
}

impl SubmapFrame {
    /// The observation drawn on this submap, when its apex lies inside.
    fn feature(&self, o: &gprflow::msg::LineObservation) -> Option<crate::plot::Feature> {
        let span = self.end_distance_m - self.start_distance_m;
        if span == 0.0 || self.cols < 2 {
            return None;
        }
        let c = (o.along_distance_m - self.start_distance_m) / span * (self.cols - 1) as f64;
        if !(0.0..=(self.cols - 1) as f64).contains(&c) {
            return None;
        }
        let row = |col: f64| {
            let dx_m = (col - c) * self.resolution_m;
            o.apex_time_ns.hypot(2.0 * dx_m / o.velocity_m_per_ns) / self.sample_interval_ns
        };
        let curve = (0..self.cols)
            .map(|j| (j as f64, row(j as f64)))
            .filter(|&(_, r)| r < self.rows as f64)
            .collect();
        Some(crate::plot::Feature {
            apex: (c, o.apex_time_ns / self.sample_interval_ns),
            curve,
            label: format!("line {}", o.line_id),
        })
    }
}

/// The observation drawn on trace columns stamped `stamps_ns` (with wheel distances
/// `distances_m` and sample interval `dt_ns`), when its apex falls between them.
fn trace_feature(
    o: &gprflow::msg::LineObservation,
    stamps_ns: &[i64],
    distances_m: &[f64],
    dt_ns: f64,
) -> Option<crate::plot::Feature> {
    let apex_ns = o.apex_stamp.to_ns();
    let (first, last) = (*stamps_ns.first()?, *stamps_ns.last()?);
    if apex_ns < first || apex_ns > last || dt_ns.is_nan() || dt_ns <= 0.0 {
        return None;
    }
    let col = stamps_ns.partition_point(|&t| t < apex_ns).min(stamps_ns.len() - 1);
    let d0 = distances_m[col];
    let moving = distances_m.iter().any(|&d| d != d0);
    let curve = if moving && o.velocity_m_per_ns > 0.0 {
        distances_m
            .iter()
            .enumerate()
            .map(|(j, d)| {
                (
                    j as f64,
                    o.apex_time_ns.hypot(2.0 * (d - d0) / o.velocity_m_per_ns) / dt_ns,
                )
            })
            .filter(|&(j, r)| (j - col as f64).abs() < 400.0 && r < 4096.0)
            .collect()
    } else {
        Vec::new()
    };
    Some(crate::plot::Feature {
        apex: (col as f64, o.apex_time_ns / dt_ns),
        curve,
        label: format!("line {}", o.line_id),
    })
}

/// Runs `gprflow radargram REC -o OUT.png`: the traces of `topic` between `from_s` and
/// `to_s` seconds after the first one, or one submap, as a picture; with the recording's
/// line observations (detected hyperbolas) drawn over it.
///
/// # Errors
/// Unreadable recording, no traces on the topic, unwritable output.
pub fn radargram_command(req: &RadargramRequest<'_>) -> Result<ExitCode> {
    use gprflow::msg::{LineObservation, Message, Samples, Submap, Sweep, Trace};
    let RadargramRequest {
        input,
        topic,
        window_s: (from_s, to_s),
        submap,
        output,
        ..
    } = *req;
    let as_columns = |trace: &Trace<'_>| -> Vec<f32> {
        match trace.samples() {
            Samples::I16(s) => s.iter().map(|&v| f32::from(v)).collect(),
            Samples::I32(s) => s.iter().map(|&v| v as f32).collect(),
            Samples::F32(s) => s.to_vec(),
        }
    };
    let is_recording = input.extension().is_some_and(|e| e.eq_ignore_ascii_case("mcap"));
    let mut traces = Vec::new();
    let topic = topic_name(topic);
    let mut what = topic.clone();
    // line observations to draw, and what places them: the submap drawn or the traces' stamps
    let mut features_topic: Option<String> = None;
    let mut observations: Vec<LineObservation> = Vec::new();
    let mut frame: Option<SubmapFrame> = None;
    let (mut stamps_ns, mut distances_m, mut sample_interval_ns) = (Vec::new(), Vec::new(), 0.0);
    if !is_recording {
        // a radar file: its traces, as the ingest stage reads them
        let options = gprflow_ingest::load::LoadOptions::default();
        let loaded = gprflow_ingest::load::load(input, gprflow_ingest::SourceFormat::Auto, &options)
            .with_context(|| format!("{}: cannot read", input.display()))?;
        let first = loaded.messages.first().map_or(0, |m| m.1);
        for (port, stamp, data) in &loaded.messages {
            let t = (stamp - first) as f64 * 1e-9;
            if *port != gprflow_ingest::load::Port::Gpr || t < from_s || to_s.is_some_and(|end| t > end) {
                continue;
            }
            let trace: Trace = gprflow::msg::decode(data)?;
            distances_m.push(trace.distance_m);
            sample_interval_ns = trace.sample_interval_ns;
            traces.push(as_columns(&trace));
        }
        what = format!("{} traces", input.display());
    } else {
        let rec = Recording::open(input)?;
        let topics = rec.topics();
        let ty = topics.iter().find(|(t, _)| *t == topic).map(|(_, ty)| ty.clone());
        features_topic = match (req.no_features, req.features) {
            (true, _) => None,
            (false, Some(f)) => {
                let f = topic_name(f);
                if !topics.iter().any(|(t, ty)| *t == f && ty == LineObservation::TYPE_NAME) {
                    bail!("{}: no {} topic `{f}`", input.display(), LineObservation::TYPE_NAME);
                }
                Some(f)
            }
            (false, None) => topics
                .iter()
                .find(|(_, ty)| ty == LineObservation::TYPE_NAME)
                .map(|(t, _)| t.clone()),
        };
        let mut first: Option<u64> = None;
        let mut failure = None;
        let mut best: Option<(f32, u32, Vec<Vec<f32>>)> = None;
        let is_submap = ty.as_deref() == Some(Submap::TYPE_NAME);
        let is_sweep = ty.as_deref() == Some(Sweep::TYPE_NAME);
        rec.scan(|m| {
            if failure.is_some() {
                return;
            }
            if features_topic.as_deref() == Some(m.topic) {
                match gprflow::msg::decode::<LineObservation>(m.data) {
                    Ok(o) => observations.push(o),
                    Err(e) => failure = Some(format!("{}: {} seq {}: {e}", input.display(), m.topic, m.sequence)),
                }
                return;
            }
            if m.topic != topic {
                return;
            }
            if is_submap {
                match gprflow::msg::decode::<Submap>(m.data) {
                    Ok(s) => {
                        let wanted = match submap {
                            Some(id) => s.id == id,
                            None => best.as_ref().is_none_or(|b| s.saliency > b.0),
                        };
                        if wanted {
                            let (rows, cols) = (s.rows as usize, s.cols as usize);
                            frame = Some(SubmapFrame {
                                start_distance_m: s.start_distance_m,
                                end_distance_m: s.end_distance_m,
                                resolution_m: s.resolution_m,
                                sample_interval_ns: s.sample_interval_ns,
                                cols,
                                rows,
                            });
                            let columns = (0..cols)
                                .map(|c| {
                                    (0..rows)
                                        .map(|r| s.pixels.get(r * cols + c).copied().unwrap_or(0.0))
                                        .collect()
                                })
                                .collect();
                            best = Some((s.saliency, s.id, columns));
                        }
                    }
                    Err(e) => failure = Some(format!("{}: {topic} seq {}: {e}", input.display(), m.sequence)),
                }
                return;
            }
            let t0 = *first.get_or_insert(m.log_time);
            let t = (m.log_time - t0) as f64 * 1e-9;
            if t < from_s || to_s.is_some_and(|end| t > end) {
                return;
            }
            if is_sweep {
                // time-domain sweeps: the middle channel
                match gprflow::msg::decode::<Sweep>(m.data) {
                    Ok(s) if s.domain == Sweep::DOMAIN_TIME && s.channel_count > 0 => {
                        sample_interval_ns = s.sample_interval_ns;
                        let n = s.bin_count as usize;
                        let ch = s.channel_count as usize / 2;
                        traces.push(
                            s.values
                                .get(ch * n..(ch + 1) * n)
                                .map(<[f32]>::to_vec)
                                .unwrap_or_default(),
                        );
                    }
                    Ok(_) => {
                        failure = Some(format!(
                            "{}: {topic}: frequency-domain sweeps (run them through lgpr_dsp first)",
                            input.display()
                        ))
                    }
                    Err(e) => failure = Some(format!("{}: {topic} seq {}: {e}", input.display(), m.sequence)),
                }
                return;
            }
            match gprflow::msg::decode::<Trace>(m.data) {
                Ok(trace) => {
                    stamps_ns.push(trace.header.stamp.to_ns());
                    distances_m.push(trace.distance_m);
                    sample_interval_ns = trace.sample_interval_ns;
                    traces.push(as_columns(&trace));
                }
                Err(e) => failure = Some(format!("{}: {topic} seq {}: {e}", input.display(), m.sequence)),
            }
        });
        if let Some(f) = failure {
            bail!(f);
        }
        if is_submap {
            let Some((saliency, id, columns)) = best else {
                bail!(
                    "{}: no submap{} on {topic}",
                    input.display(),
                    submap.map(|i| format!(" with id {i}")).unwrap_or_default()
                );
            };
            traces = columns;
            what = format!("submap {id} (saliency {saliency:.3}) of {topic}");
            if let Some(f) = frame {
                let n = f.cols.max(2) - 1;
                distances_m = (0..f.cols)
                    .map(|c| f.start_distance_m + (f.end_distance_m - f.start_distance_m) * c as f64 / n as f64)
                    .collect();
                sample_interval_ns = f.sample_interval_ns;
            }
        }
    }
    if traces.is_empty() {
        bail!("{}: no traces on {topic} in that time window", input.display());
    }
    let features: Vec<crate::plot::Feature> = match frame {
        Some(f) => observations.iter().filter_map(|o| f.feature(o)).collect(),
        None if stamps_ns.len() == traces.len() => observations
            .iter()
            .filter_map(|o| trace_feature(o, &stamps_ns, &distances_m, sample_interval_ns))
            .collect(),
        None => Vec::new(),
    };
    // a submap's distances fall when it was driven backwards (its columns are in ground
    // order): then the axis counts metres from its first column
    let distances_m = (distances_m.len() == traces.len())
        .then_some(distances_m)
        .and_then(|mut d| {
            if let (Some(&first), true) = (d.first(), frame.is_some() && d.first() > d.last()) {
                d.iter_mut().for_each(|v| *v = first - *v);
            }
            crate::plot::usable_distances(&d).then_some(d)
        });
    crate::plot::radargram(
        output,
        &crate::plot::Radargram {
            title: &format!("{what}: {} columns", traces.len()),
            traces: &traces,
            distances_m,
            sample_interval_ns: (sample_interval_ns.is_finite() && sample_interval_ns > 0.0)
                .then_some(sample_interval_ns),
            velocity_m_per_ns: req.velocity_m_per_ns,
            remove_background: !req.keep_background,
            gain: req.gain,
            clip_percentile: req.clip_percentile,
            colormap: req.colormap,
            features: &features,
        },
    )?;
    let drawn = match &features_topic {
        Some(t) => format!(" with {} line observations of {t}", features.len()),
        None => String::new(),
    };
    writeln!(
        std::io::stdout().lock(),
        "{} columns of {what}{drawn} drawn to {}",
        traces.len(),
        output.display()
    )?;
    Ok(ExitCode::SUCCESS)
}

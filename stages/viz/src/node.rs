//! The `viz` stage: what a graph's run looks like in Foxglove.

use std::borrow::Cow;
use std::collections::VecDeque;

use gprflow_msg::{Header, Image, Message, Path, PoseStamped, Samples, StateEstimate, Submap, Trace, Trajectory};
use gprflow_stage::{Input, InputPorts, InputSpec, Output, Outputs, ParamError, PortSpec, Ports, Stage, StageError};

use super::{Gain, Rendering, amplitudes, mono8};

/// Parameters of [`VizStage`].
#[derive(Debug, Clone, serde::Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct VizParams {
    /// Traces across the rolling radargram (default 400).
    pub window_traces: usize,
    /// Publish the radargram every this many traces (default 50).
    pub every_traces: usize,
    /// Gain with depth of the radargram (default linear; none, linear or agc).
    pub gain: Gain,
    /// Percentile of magnitudes at black and white (default 99).
    pub clip_percentile: f64,
}

impl Default for VizParams {
    fn default() -> Self {
        Self {
            window_traces: 400,
            every_traces: 50,
            gain: Gain::Linear,
            clip_percentile: 99.0,
        }
    }
}

/// Publishes pictures of what it reads, each input optional: traces as a rolling radargram
/// (`radargram`, mono8, the newest trace on the right, background removed over the window),
/// submaps as images (`submap`, mono8, clipped at the 99th percentile), trajectory snapshots
/// as `nav_msgs/Path` (`path`) and state estimates as `geometry_msgs/PoseStamped` (`pose`).
#[derive(Debug)]
pub struct VizStage {
    params: VizParams,
    window: VecDeque<Vec<f32>>,
    traces: u64,
    radargram: Output<Image<'static>>,
    submap: Output<Image<'static>>,
    path: Output<Path>,
    pose: Output<PoseStamped>,
}

/// A mono8 image of `values` (column-major) stamped `header`.
fn image(header: Header, values: &[Vec<f64>], full_scale: f64) -> Image<'static> {
    let (width, height) = (values.len(), values.first().map_or(0, Vec::len));
    Image {
        header,
        height: u32::try_from(height).unwrap_or(u32::MAX),
        width: u32::try_from(width).unwrap_or(u32::MAX),
        encoding: "mono8".to_owned(),
        is_bigendian: 0,
        step: u32::try_from(width).unwrap_or(u32::MAX),
        data: Cow::Owned(mono8(values, full_scale)),
    }
}

impl VizStage {
    fn on_trace(&mut self, trace: &Trace<'_>, out: &mut Outputs) -> Result<(), StageError> {
        let column = match trace.samples() {
            Samples::I16(s) => s.iter().map(|&v| f32::from(v)).collect(),
            Samples::I32(s) => s.iter().map(|&v| v as f32).collect(),
            Samples::F32(s) => s.to_vec(),
        };
        if self.window.len() == self.params.window_traces {
            self.window.pop_front();
        }
        self.window.push_back(column);
        self.traces += 1;
        if !self.traces.is_multiple_of(self.params.every_traces as u64) {
            return Ok(());
        }
        let how = Rendering {
            remove_background: true,
            gain: self.params.gain,
            clip_percentile: self.params.clip_percentile,
        };
        let columns: Vec<&[f32]> = self.window.iter().map(Vec::as_slice).collect();
        match amplitudes(&columns, &how) {
            Ok((values, full_scale)) => out.send(self.radargram, &image(trace.header.clone(), &values, full_scale)),
            // traces with no samples: nothing to show
            Err(_) => Ok(()),
        }
    }

    fn on_submap(&mut self, s: &Submap<'_>, out: &mut Outputs) -> Result<(), StageError> {
        let (rows, cols) = (s.rows as usize, s.cols as usize);
        if rows == 0 || cols == 0 || s.pixels.len() != rows * cols {
            return Ok(());
        }
        let columns: Vec<Vec<f32>> = (0..cols)
            .map(|c| (0..rows).map(|r| s.pixels[r * cols + c]).collect())
            .collect();
        let how = Rendering {
            remove_background: false,
            gain: Gain::None,
            clip_percentile: self.params.clip_percentile,
        };
        match amplitudes(&columns, &how) {
            Ok((values, full_scale)) => out.send(self.submap, &image(s.header.clone(), &values, full_scale)),
            Err(_) => Ok(()),
        }
    }
}

impl Stage for VizStage {
    type Params = VizParams;
    const NAME: &'static str = "viz";
    const ABOUT: &'static str = "radargrams and submaps as sensor_msgs/Image, the trajectory as nav_msgs/Path, states as PoseStamped (for Foxglove)";

    fn inputs() -> InputPorts {
        let optional = |name: &str, msg_type: &str| InputSpec {
            port: PortSpec::new(name, msg_type),
            optional: true,
        };
        InputPorts::Fixed(vec![
            optional("trace", Trace::TYPE_NAME),
            optional("submap", Submap::TYPE_NAME),
            optional("trajectory", Trajectory::TYPE_NAME),
            optional("state", StateEstimate::TYPE_NAME),
        ])
    }

    fn outputs(_: &Self::Params) -> Result<Vec<PortSpec>, ParamError> {
        Ok(vec![
            PortSpec::new("radargram", Image::TYPE_NAME),
            PortSpec::new("submap", Image::TYPE_NAME),
            PortSpec::new("path", Path::TYPE_NAME),
            PortSpec::new("pose", PoseStamped::TYPE_NAME),
        ])
    }

    fn check_params(params: &Self::Params) -> Result<(), ParamError> {
        let positive = |name: &str, v: usize| {
            if v == 0 {
                Err(ParamError {
                    path: vec![name.to_owned()],
                    message: "must be at least 1".to_owned(),
                })
            } else {
                Ok(())
            }
        };
        positive("window_traces", params.window_traces)?;
        positive("every_traces", params.every_traces)?;
        if !(params.clip_percentile > 0.0 && params.clip_percentile <= 100.0) {
            return Err(ParamError {
                path: vec!["clip_percentile".to_owned()],
                message: format!("{} is not in (0, 100]", params.clip_percentile),
            });
        }
        Ok(())
    }

    fn create(params: Self::Params, ports: &Ports) -> Result<Self, StageError> {
        Ok(Self {
            window: VecDeque::with_capacity(params.window_traces),
            params,
            traces: 0,
            radargram: ports.output("radargram")?,
            submap: ports.output("submap")?,
            path: ports.output("path")?,
            pose: ports.output("pose")?,
        })
    }

    fn on_message(&mut self, input: Input<'_>, out: &mut Outputs) -> Result<(), StageError> {
        match input.name() {
            "trace" => self.on_trace(&input.decode()?, out),
            "submap" => self.on_submap(&input.decode()?, out),
            "trajectory" => {
                let t: Trajectory = input.decode()?;
                let path = Path {
                    header: t.header,
                    poses: t.poses,
                };
                out.send(self.path, &path)
            }
            _ => {
                let s: StateEstimate = input.decode()?;
                let pose = PoseStamped {
                    header: s.header,
                    pose: s.world_from_body.pose,
                };
                out.send(self.pose, &pose)
            }
        }
    }
}

//! The `submap` stage: traces, wheel odometry and IMU in (merged in stamp order by the
//! runtime), [`Submap`](gprflow_msg::Submap) messages out.

use std::borrow::Cow;

use gprflow_msg::{
    Header, Imu, Message, Point, Pose, Quaternion, Samples, Submap as SubmapMsg, Time, Trace, WheelOdometry,
};
use gprflow_stage::{
    Drops, Input, InputPorts, InputSpec, Output, Outputs, ParamError, PortSpec, Ports, Stage, StageError,
};

use gprflow_geometry::Planar;

use crate::{Error, Submap, SubmapBuilder, SubmapParams};

/// The submap stage.
#[derive(Debug)]
pub struct SubmapStage {
    builder: SubmapBuilder,
    out: Output<SubmapMsg<'static>>,
    sample_interval_ns: f64,
    drops: Drops,
    scratch: Vec<f32>,
}

fn pose_msg(p: &Planar) -> Pose {
    let half = 0.5 * p.yaw_rad;
    Pose {
        position: Point {
            x: p.x_m,
            y: p.y_m,
            z: 0.0,
        },
        orientation: Quaternion {
            x: 0.0,
            y: 0.0,
            z: half.sin(),
            w: half.cos(),
        },
    }
}

/// The message of a submap (`header.stamp` = its newest trace, frame `odom`); the pixels
/// move into it.
pub fn submap_msg(s: Submap, sample_interval_ns: f64) -> SubmapMsg<'static> {
    SubmapMsg {
        header: Header::new(s.end_stamp_ns, "odom"),
        id: s.id,
        start_stamp: Time::from_ns(s.start_stamp_ns),
        start_distance_m: s.start_distance_m,
        end_distance_m: s.end_distance_m,
        resolution_m: s.resolution_m,
        sample_interval_ns,
        rows: s.rows as u32,
        cols: s.cols as u32,
        start_pose: pose_msg(&s.start_pose),
        end_pose: pose_msg(&s.end_pose),
        saliency: s.saliency,
        valid: s.valid,
        pixels: Cow::Owned(s.pixels),
        column_stamps_ns: Cow::Owned(s.column_stamps_ns),
    }
}

impl SubmapStage {
    fn accept<T>(&mut self, input: &Input<'_>, r: crate::Result<T>) -> Result<Option<T>, StageError> {
        match r {
            Ok(v) => Ok(Some(v)),
            Err(Error::BadMeasurement(why)) => {
                self.drops.record(Self::NAME, input, &why);
                Ok(None)
            }
            Err(e) => Err(StageError::failed(e)),
        }
    }

    fn publish(&mut self, maps: Vec<Submap>, out: &mut Outputs) -> Result<(), StageError> {
        for m in maps {
            out.send(self.out, &submap_msg(m, self.sample_interval_ns))?;
        }
        Ok(())
    }
}

impl Stage for SubmapStage {
    type Params = SubmapParams;
    const NAME: &'static str = "submap";
    const ABOUT: &'static str =
        "odometry-based submaps: traces resampled uniformly along track by wheel distance, validity rule, saliency";

    fn inputs() -> InputPorts {
        let port = |name: &str, ty: &str, optional: bool| InputSpec {
            port: PortSpec::new(name, ty),
            optional,
        };
        InputPorts::Fixed(vec![
            port("trace", Trace::TYPE_NAME, false),
            port("wheel", WheelOdometry::TYPE_NAME, false),
            // z gyro and y accelerometer for the validity rule and the heading
            port("imu", Imu::TYPE_NAME, true),
        ])
    }

    fn outputs(_: &Self::Params) -> Result<Vec<PortSpec>, ParamError> {
        Ok(vec![PortSpec::new("submap", SubmapMsg::TYPE_NAME)])
    }

    fn check_params(params: &Self::Params) -> Result<(), ParamError> {
        params.check()
    }

    fn create(params: Self::Params, ports: &Ports) -> Result<Self, StageError> {
        let builder = SubmapBuilder::new(params).map_err(StageError::failed)?;
        if ports.input("imu").is_none() {
            tracing::info!("submap: no imu input: the validity rule checks the encoder only, poses keep heading 0");
        }
        Ok(Self {
            builder,
            out: ports.output("submap")?,
            sample_interval_ns: f64::NAN,
            drops: Drops::new(),
            scratch: Vec::new(),
        })
    }

    fn on_message(&mut self, input: Input<'_>, out: &mut Outputs) -> Result<(), StageError> {
        let stamp = input.stamp_ns();
        let maps = match input.name() {
            "trace" => {
                let t: Trace = input.decode()?;
                if self.sample_interval_ns.is_nan() {
                    self.sample_interval_ns = t.sample_interval_ns;
                }
                let r = match t.samples() {
                    Samples::F32(s) => self.builder.trace(stamp, s),
                    Samples::I16(s) => {
                        self.scratch.clear();
                        self.scratch.extend(s.iter().map(|&v| f32::from(v)));
                        self.builder.trace(stamp, &self.scratch)
                    }
                    Samples::I32(s) => {
                        self.scratch.clear();
                        self.scratch.extend(s.iter().map(|&v| v as f32));
                        self.builder.trace(stamp, &self.scratch)
                    }
                };
                self.accept(&input, r)?
            }
            "wheel" => {
                let w: WheelOdometry = input.decode()?;
                let r = self.builder.wheel(stamp, w.distance_m);
                self.accept(&input, r)?
            }
            "imu" => {
                let m: Imu = input.decode()?;
                let r = self.builder.imu(stamp, m.angular_velocity.z, m.linear_acceleration.y);
                self.accept(&input, r)?;
                None
            }
            _ => None,
        };
        if let Some(maps) = maps {
            self.publish(maps, out)?;
        }
        Ok(())
    }

    fn finish(&mut self, out: &mut Outputs) -> Result<(), StageError> {
        let maps = self.builder.finish();
        self.publish(maps, out)?;
        let s = self.builder.stats();
        tracing::info!(
            valid = s.valid,
            invalid = s.invalid,
            traces = s.traces,
            "submap: {} valid submaps, {} failed the validity rule (not emitted unless emit_invalid)",
            s.valid,
            s.invalid
        );
        if s.traces_without_wheel > 0 {
            tracing::warn!(
                traces = s.traces_without_wheel,
                "submap: traces that never saw a wheel distance, not used"
            );
        }
        self.drops.report(Self::NAME);
        Ok(())
    }
}

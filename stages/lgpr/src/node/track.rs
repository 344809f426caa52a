//! The `lgpr_track` stage (seed 001 §2.2.2): every processed sweep registered against the
//! prior map in five degrees of freedom ([`Tracker`]) on the local grid around the vehicle
//! ([`GridPager`]: gridded in the background, two grids in memory), seeded by the GPS/INS;
//! one `MapFix` out per sweep with its correlation, overlap, lock state and covariance.

use std::path::PathBuf;

use gprflow_msg::{Covariance6, Header, MapFix, Message, Odometry, Point, Pose, Quaternion, Sweep};
use gprflow_stage::{
    Drops, Input, InputPorts, InputSpec, Output, Outputs, ParamError, PortSpec, Ports, Stage, StageError,
};
use serde::Deserialize;

use super::map::{to_param, yaw_of};
use crate::array::ArrayGeometry;
use crate::map::{GridPager, GridSpec, MapReader};
use crate::track::{InsState, Miss, TrackParams, Tracker};

/// Parameters of `lgpr_track`.
#[derive(Debug, Clone, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct LgprTrackParams {
    /// The map directory (written by `lgpr_map`).
    pub map: PathBuf,
    /// The array's geometry on the vehicle.
    #[serde(default)]
    pub array: ArrayGeometry,
    /// The local grid.
    #[serde(default)]
    pub grid: GridSpec,
    /// The tracker: correlation window, search boxes, swarm, lock criteria.
    #[serde(default)]
    pub tracker: TrackParams,
    /// A GPS/INS fix older than this at a sweep is not used to predict (the sweep is dropped),
    /// s. Default 1.
    #[serde(default = "default_ins_age")]
    pub max_ins_age_s: f64,
}

fn default_ins_age() -> f64 {
    1.0
}

/// Per-run counts for the summary.
#[derive(Debug, Default)]
struct Counts {
    sweeps: u64,
    locked: u64,
    misses: [u64; 3],
    no_ins: u64,
    evaluations: u64,
}

/// The `lgpr_track` stage.
#[derive(Debug)]
pub struct LgprTrackStage {
    params: LgprTrackParams,
    map: MapReader,
    pager: Option<GridPager>,
    /// Made at the first sweep (its channel count).
    tracker: Option<Tracker>,
    ins: Option<(i64, InsState)>,
    out: Output<MapFix>,
    counts: Counts,
    drops: Drops,
    damage_reported: usize,
    /// The lock state of the last fix, for logging its changes.
    was_locked: bool,
}

/// This process's peak resident set, MB (Linux: `VmHWM` of `/proc/self/status`).
fn peak_rss_mb() -> Option<f64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kb: f64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb / 1024.0)
}

/// Orientation of a pose with heading `yaw` and roll `roll` (roll about x, then yaw about z).
fn orientation(yaw: f64, roll: f64) -> Quaternion {
    let (sy, cy) = (yaw / 2.0).sin_cos();
    let (sr, cr) = (roll / 2.0).sin_cos();
    Quaternion {
        x: cy * sr,
        y: sy * sr,
        z: sy * cr,
        w: cy * cr,
    }
}

impl LgprTrackStage {
    fn on_sweep(&mut self, input: &Input<'_>, s: &Sweep<'_>, out: &mut Outputs) -> Result<(), StageError> {
        let samples = self.map.info().samples as usize;
        if s.domain != Sweep::DOMAIN_TIME {
            self.drops.record(
                Self::NAME,
                input,
                &format_args!("domain {}: not a time-domain sweep", s.domain),
            );
            return Ok(());
        }
        if s.bin_count as usize != samples
            || (s.sample_interval_ns - self.map.info().sample_interval_ns).abs() > 1e-6 * s.sample_interval_ns.abs()
        {
            self.drops.record(
                Self::NAME,
                input,
                &format_args!(
                    "{} samples {} ns apart; the map has {samples} samples {} ns apart",
                    s.bin_count,
                    s.sample_interval_ns,
                    self.map.info().sample_interval_ns
                ),
            );
            return Ok(());
        }
        let channels = s.channel_count as usize;
        let tracker = self
            .tracker
            .get_or_insert_with(|| Tracker::new(self.params.tracker.clone(), &self.params.array, channels));
        if tracker.channels() != channels || s.values.len() != channels * samples {
            self.drops.record(
                Self::NAME,
                input,
                &format_args!(
                    "{channels} channels, {} values: the first sweep had {} channels of {samples} samples",
                    s.values.len(),
                    tracker.channels()
                ),
            );
            return Ok(());
        }
        if let Some(n) = s.values.iter().position(|v| !v.is_finite()) {
            self.drops.record(
                Self::NAME,
                input,
                &format_args!("channel {} sample {} is {}", n / samples, n % samples, s.values[n]),
            );
            return Ok(());
        }
        let stamp = input.stamp_ns();
        let Some((ins_stamp, ins)) = self.ins else {
            self.counts.no_ins += 1;
            return Ok(());
        };
        if (stamp - ins_stamp) as f64 * 1e-9 > self.params.max_ins_age_s {
            self.counts.no_ins += 1;
            return Ok(());
        }
        let Some(tracker) = self.tracker.as_mut() else {
            return Ok(());
        };
        let expected = tracker.expect(stamp, &ins);
        let speed = ins.velocity_mps[0].hypot(ins.velocity_mps[1]);
        let direction = if speed > 0.1 {
            [ins.velocity_mps[0] / speed, ins.velocity_mps[1] / speed]
        } else {
            [0.0, 0.0]
        };
        let pager = self.pager.get_or_insert_with(|| {
            GridPager::new(
                self.map.clone(),
                self.params.grid.clone(),
                self.params.tracker.window_len,
            )
        });
        let events = pager
            .update([expected[0], expected[1]], direction)
            .map_err(StageError::failed)?;
        if events.stalled {
            // expected when a recording replays faster than the vehicle drove; counted in the
            // summary (`stalls`), a latency to watch live
            tracing::debug!(seq = input.seq(), "lgpr_track: waited for the next grid");
        }
        for d in &pager.damage[self.damage_reported..] {
            tracing::warn!("lgpr_track: map damage: {d}");
        }
        self.damage_reported = pager.damage.len();
        let Some(grid) = pager.current().cloned() else {
            return Ok(());
        };
        let Some(r) = tracker.track(&grid, s.sample_interval_ns, &s.values, samples, stamp, &ins) else {
            return Ok(());
        };
        self.counts.sweeps += 1;
        self.counts.evaluations += r.evaluations as u64;
        match r.miss {
            None => self.counts.locked += 1,
            Some(Miss::Correlation) => self.counts.misses[0] += 1,
            Some(Miss::Overlap) => self.counts.misses[1] += 1,
            Some(Miss::Gate) => self.counts.misses[2] += 1,
        }
        if r.locked != self.was_locked {
            tracing::debug!(
                stamp,
                correlation = r.correlation,
                overlap = r.overlap,
                miss = ?r.miss,
                "lgpr_track: {}",
                if r.locked { "locked" } else { "lost lock" }
            );
            self.was_locked = r.locked;
        }
        let [x, y, dh, yaw, roll] = r.pose;
        let t = &self.params.tracker;
        let mut cov = [0.0; 36];
        let diag = [
            r.sigma_m * r.sigma_m,
            r.sigma_m * r.sigma_m,
            (t.search_max.height_m / 2.0).powi(2),
            (t.search_max.roll_deg.to_radians() / 2.0).powi(2),
            1.0, // pitch: not estimated
            (t.search_max.heading_deg.to_radians() / 2.0).powi(2),
        ];
        for (i, v) in diag.iter().enumerate() {
            cov[i * 7] = *v;
        }
        let msg = MapFix {
            header: Header::new(stamp, "world"),
            world_from_body: Pose {
                position: Point { x, y, z: dh },
                orientation: orientation(yaw, roll),
            },
            covariance: Covariance6(cov),
            correlation: r.correlation as f32,
            overlapping_channels: r.overlap,
            locked: r.locked,
        };
        out.send(self.out, &msg)
    }
}

impl Stage for LgprTrackStage {
    type Params = LgprTrackParams;
    const NAME: &'static str = "lgpr_track";
    const ABOUT: &'static str = "LGPR tracking: each sweep registered in 5 DOF against the prior map's local grid by particle swarm; map fixes out";

    fn inputs() -> InputPorts {
        let port = |name: &str, ty: &str| InputSpec {
            port: PortSpec::new(name, ty),
            optional: false,
        };
        InputPorts::Fixed(vec![port("ins", Odometry::TYPE_NAME), port("sweep", Sweep::TYPE_NAME)])
    }

    fn outputs(_: &Self::Params) -> Result<Vec<PortSpec>, ParamError> {
        Ok(vec![PortSpec::new("map_fix", MapFix::TYPE_NAME)])
    }

    fn check_params(p: &Self::Params) -> Result<(), ParamError> {
        if p.map.as_os_str().is_empty() {
            return Err(ParamError::new("map", "must name a map directory"));
        }
        p.array.check("array").map_err(to_param)?;
        p.grid.check("grid").map_err(to_param)?;
        p.tracker.check().map_err(|e| to_param(e).within("tracker"))?;
        gprflow_stage::params::positive("max_ins_age_s", p.max_ins_age_s)?;
        Ok(())
    }

    fn create(params: Self::Params, ports: &Ports) -> Result<Self, StageError> {
        let map = MapReader::open(&params.map).map_err(StageError::failed)?;
        let samples = map.info().samples as usize;
        let t = &params.tracker;
        if t.window_start + t.window_len > samples {
            return Err(StageError::failed(format!(
                "lgpr_track: tracker.window_start + window_len = {} is past the map's {samples} samples",
                t.window_start + t.window_len
            )));
        }
        let tiles = map.tiles().map_err(StageError::failed)?;
        tracing::info!(
            map = %params.map.display(),
            tiles = tiles.len(),
            columns = map.info().columns,
            "lgpr_track: map opened"
        );
        Ok(Self {
            tracker: None,
            params,
            map,
            pager: None,
            ins: None,
            out: ports.output("map_fix")?,
            counts: Counts::default(),
            drops: Drops::new(),
            damage_reported: 0,
            was_locked: false,
        })
    }

    fn on_message(&mut self, input: Input<'_>, out: &mut Outputs) -> Result<(), StageError> {
        match input.name() {
            "ins" => {
                let m: Odometry = input.decode()?;
                let p = &m.pose.pose;
                let yaw = yaw_of(&p.orientation);
                let v = &m.twist.twist.linear;
                let (s, c) = yaw.sin_cos();
                let state = InsState {
                    xy_m: [p.position.x, p.position.y],
                    yaw_rad: yaw,
                    velocity_mps: [c * v.x - s * v.y, s * v.x + c * v.y],
                };
                let finite = state.xy_m.iter().chain(&state.velocity_mps).all(|v| v.is_finite()) && yaw.is_finite();
                if finite {
                    self.ins = Some((input.stamp_ns(), state));
                } else {
                    self.drops
                        .record(Self::NAME, &input, &"non-finite position, orientation or velocity");
                }
            }
            "sweep" => {
                let s: Sweep = input.decode()?;
                self.on_sweep(&input, &s, out)?;
            }
            _ => {}
        }
        Ok(())
    }

    fn finish(&mut self, _out: &mut Outputs) -> Result<(), StageError> {
        self.drops.report(Self::NAME);
        let c = &self.counts;
        let pct = |n: u64| {
            if c.sweeps > 0 {
                100.0 * n as f64 / c.sweeps as f64
            } else {
                0.0
            }
        };
        let (grids, grid_p50_ms, grid_max_ms, stalls) = match &self.pager {
            Some(p) => {
                let mut t = p.grid_times_s.clone();
                t.sort_by(f64::total_cmp);
                let p50 = t.get(t.len() / 2).copied().unwrap_or(0.0) * 1e3;
                let max = t.last().copied().unwrap_or(0.0) * 1e3;
                (t.len(), p50, max, p.stalls)
            }
            None => (0, 0.0, 0.0, 0),
        };
        tracing::info!(
            sweeps = c.sweeps,
            locked_pct = format!("{:.2}", pct(c.locked)),
            low_correlation = c.misses[0],
            low_overlap = c.misses[1],
            gated = c.misses[2],
            without_ins = c.no_ins,
            evaluations_per_sweep = format!(
                "{:.0}",
                if c.sweeps > 0 {
                    c.evaluations as f64 / c.sweeps as f64
                } else {
                    0.0
                }
            ),
            grids,
            grid_p50_ms = format!("{grid_p50_ms:.0}"),
            grid_max_ms = format!("{grid_max_ms:.0}"),
            stalls,
            stretch = format!("{:.3}", self.tracker.as_ref().map_or(1.0, Tracker::stretch)),
            peak_rss_mb = peak_rss_mb().map_or_else(|| "unknown".to_owned(), |v| format!("{v:.0}")),
            "lgpr_track: done"
        );
        Ok(())
    }
}

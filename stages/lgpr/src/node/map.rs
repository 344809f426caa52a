//! The `lgpr_map` stage (seed 001 §2.2): processed sweeps of a mapping pass placed by the
//! GPS/INS (or, when asked, by any pose source such as the ground truth) and written to a map
//! store, each channel's column at its element's world position.
//!
//! A sweep is placed by interpolating the two poses around its stamp, so it waits (at most
//! one pose interval) for the pose after it. Sweeps before the first pose or after the last
//! cannot be placed and are counted, as are unusable sweeps (wrong domain, sizes, NaN).
//!
//! Placed by map fixes instead (the `fix` input: `lgpr_track`'s registrations of the same
//! sweeps against an existing map, `graphs/lgpr-map-align.yaml`), a pass is written in that
//! map's frame: each sweep at its own fix's pose, and only where the fix is locked. This is
//! the cross-pass alignment seed 001 §2.2 names against ghosting: two passes placed each by
//! its own GPS/INS disagree by the GPS/INS's error (decimetres), and a grid that mixes them
//! blurs. Sweeps without a fix or with an unlocked one are counted and left out.

use std::collections::VecDeque;
use std::path::PathBuf;

use gprflow_msg::{MapFix, Message, Odometry, PoseStamped, Quaternion, Sweep};
use gprflow_stage::{Drops, Input, InputPorts, InputSpec, Outputs, ParamError, PortSpec, Ports, Stage, StageError};
use serde::Deserialize;

use crate::array::ArrayGeometry;
use crate::map::MapWriter;

/// Parameters of `lgpr_map`.
#[derive(Debug, Clone, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct LgprMapParams {
    /// The map directory: created, or opened to add this pass.
    pub map: PathBuf,
    /// The array's geometry on the vehicle.
    #[serde(default)]
    pub array: ArrayGeometry,
    /// Tile size of a new map, m. Default 50.
    #[serde(default = "default_tile")]
    pub tile_m: f64,
    /// Skip sweeps less than this far (m) from the last one written (0: keep every sweep;
    /// seed 001 §2.2 notes sparser maps may do). Default 0.
    #[serde(default)]
    pub min_spacing_m: f64,
}

/// Steps of the driven length, m (see `LgprMapStage::length_from`).
const LENGTH_STEP_M: f64 = 0.5;

fn default_tile() -> f64 {
    50.0
}

/// A pose at a stamp: world position and heading.
#[derive(Debug, Clone, Copy)]
struct Placed {
    stamp_ns: i64,
    x: f64,
    y: f64,
    yaw: f64,
}

/// Heading of a unit quaternion.
pub(crate) fn yaw_of(q: &Quaternion) -> f64 {
    (2.0 * (q.w * q.z + q.x * q.y)).atan2(1.0 - 2.0 * (q.y * q.y + q.z * q.z))
}

fn interpolate(a: &Placed, b: &Placed, stamp_ns: i64) -> Placed {
    let span = (b.stamp_ns - a.stamp_ns) as f64;
    let f = if span > 0.0 {
        (stamp_ns - a.stamp_ns) as f64 / span
    } else {
        0.0
    };
    let mut dyaw = b.yaw - a.yaw;
    dyaw = (dyaw + std::f64::consts::PI).rem_euclid(std::f64::consts::TAU) - std::f64::consts::PI;
    Placed {
        stamp_ns,
        x: a.x + f * (b.x - a.x),
        y: a.y + f * (b.y - a.y),
        yaw: a.yaw + f * dyaw,
    }
}

/// Sweeps paired with the map fixes of the same stamp (both arrive in stamp order): a locked
/// fix places its sweep, an unlocked one leaves it out, a sweep that a later fix has passed got
/// none, and a fix whose sweep never came (dropped as unusable) is let go.
#[derive(Debug)]
struct FixMatcher<S> {
    sweeps: VecDeque<(i64, S)>,
    /// The fixes not yet paired: the locked ones' poses (None: not locked).
    fixes: VecDeque<(i64, Option<Placed>)>,
    /// Sweeps left out: with an unlocked fix, without a fix.
    unlocked: u64,
    no_fix: u64,
}

impl<S> Default for FixMatcher<S> {
    fn default() -> Self {
        Self {
            sweeps: VecDeque::new(),
            fixes: VecDeque::new(),
            unlocked: 0,
            no_fix: 0,
        }
    }
}

impl<S> FixMatcher<S> {
    fn sweep(&mut self, stamp_ns: i64, sweep: S) {
        self.sweeps.push_back((stamp_ns, sweep));
    }

    /// A fix at or before the last one is ignored.
    fn fix(&mut self, stamp_ns: i64, placed: Option<Placed>) {
        if self.fixes.back().is_none_or(|(last, _)| *last < stamp_ns) {
            self.fixes.push_back((stamp_ns, placed));
        }
    }

    /// The next sweep with its locked fix's pose, once both have come.
    fn next_placed(&mut self) -> Option<(Placed, S)> {
        loop {
            let (&(sweep_ns, _), &(fix_ns, placed)) = (self.sweeps.front()?, self.fixes.front()?);
            if fix_ns < sweep_ns {
                self.fixes.pop_front();
                continue;
            }
            let (_, sweep) = self.sweeps.pop_front()?;
            if fix_ns > sweep_ns {
                self.no_fix += 1;
                continue;
            }
            self.fixes.pop_front();
            match placed {
                Some(at) => return Some((at, sweep)),
                None => self.unlocked += 1,
            }
        }
    }

    /// The sweeps still waiting got no fix.
    fn finish(&mut self) {
        self.no_fix += self.sweeps.len() as u64;
        self.sweeps.clear();
    }
}

/// The `lgpr_map` stage.
#[derive(Debug)]
pub struct LgprMapStage {
    params: LgprMapParams,
    writer: Option<MapWriter>,
    /// The last pose and the one before.
    poses: (Option<Placed>, Option<Placed>),
    /// Placed by map fixes (the `fix` input) instead of poses: sweeps (channels, samples)
    /// waiting for their fix.
    by_fix: Option<FixMatcher<(usize, Vec<f32>)>>,
    /// Sweeps waiting for the pose after them: (stamp, seq, channels, samples).
    waiting: VecDeque<(i64, u64, usize, Vec<f32>)>,
    samples: usize,
    sample_interval_ns: f64,
    last_written: Option<(f64, f64)>,
    /// Where the driven length was last measured from: it is added in steps of at least
    /// [`LENGTH_STEP_M`], so that the centimetres by which map fixes scatter from sweep to
    /// sweep (3.5 cm apart at 16 km/h) do not add up to length.
    length_from: Option<(f64, f64)>,
    sweeps_written: u64,
    before_first_pose: u64,
    skipped_close: u64,
    drops: Drops,
}

impl LgprMapStage {
    fn on_pose(&mut self, p: Placed) -> Result<(), StageError> {
        if let Some(last) = self.poses.1
            && p.stamp_ns <= last.stamp_ns
        {
            return Ok(());
        }
        self.poses = (self.poses.1, Some(p));
        let (Some(a), Some(b)) = self.poses else {
            return Ok(());
        };
        while let Some(&(stamp, _, _, _)) = self.waiting.front() {
            if stamp > b.stamp_ns {
                break;
            }
            let Some((stamp, _seq, channels, values)) = self.waiting.pop_front() else {
                break;
            };
            if stamp < a.stamp_ns {
                self.before_first_pose += 1;
                continue;
            }
            self.write(&interpolate(&a, &b, stamp), channels, &values)?;
        }
        Ok(())
    }

    /// Writes the sweeps whose locked fix has come.
    fn place_by_fixes(&mut self) -> Result<(), StageError> {
        while let Some((at, (channels, values))) = self.by_fix.as_mut().and_then(FixMatcher::next_placed) {
            self.write(&at, channels, &values)?;
        }
        Ok(())
    }

    fn write(&mut self, at: &Placed, channels: usize, values: &[f32]) -> Result<(), StageError> {
        let (bx, by) = (self.params.array.mount_m[0], self.params.array.mount_m[1]);
        let centre = ArrayGeometry::to_world(at.x, at.y, at.yaw, bx, by);
        if let Some(prev) = self.last_written {
            let step = (centre.0 - prev.0).hypot(centre.1 - prev.1);
            if step < self.params.min_spacing_m {
                self.skipped_close += 1;
                return Ok(());
            }
        }
        let writer = match &mut self.writer {
            Some(w) => w,
            None => {
                let w = MapWriter::open(
                    &self.params.map,
                    self.params.tile_m,
                    self.samples as u32,
                    self.sample_interval_ns,
                )
                .map_err(StageError::failed)?;
                tracing::info!(map = %self.params.map.display(), pass = w.info().passes, "lgpr_map: writing");
                self.writer.insert(w)
            }
        };
        match self.length_from {
            Some(from) => {
                let step = (centre.0 - from.0).hypot(centre.1 - from.1);
                if step >= LENGTH_STEP_M {
                    writer.add_length(step);
                    self.length_from = Some(centre);
                }
            }
            None => self.length_from = Some(centre),
        }
        for k in 0..channels {
            let (x, y) = ArrayGeometry::to_world(at.x, at.y, at.yaw, bx, self.params.array.channel_y_m(k, channels));
            let column = &values[k * self.samples..(k + 1) * self.samples];
            writer
                .push(x, y, at.stamp_ns, k as u16, column)
                .map_err(StageError::failed)?;
        }
        self.last_written = Some(centre);
        self.sweeps_written += 1;
        Ok(())
    }

    fn on_sweep(&mut self, input: &Input<'_>, s: &Sweep<'_>) {
        if s.domain != Sweep::DOMAIN_TIME {
            self.drops.record(
                Self::NAME,
                input,
                &format_args!("domain {}: not a time-domain sweep", s.domain),
            );
            return;
        }
        let (channels, samples) = (s.channel_count as usize, s.bin_count as usize);
        if channels == 0 || samples == 0 || s.values.len() != channels * samples {
            self.drops.record(
                Self::NAME,
                input,
                &format_args!("{} values for {channels} channels x {samples} samples", s.values.len()),
            );
            return;
        }
        if self.samples == 0 {
            self.samples = samples;
            self.sample_interval_ns = s.sample_interval_ns;
        } else if samples != self.samples || s.sample_interval_ns != self.sample_interval_ns {
            self.drops.record(
                Self::NAME,
                input,
                &format_args!(
                    "{samples} samples {} ns apart, the pass so far {} {} ns apart",
                    s.sample_interval_ns, self.samples, self.sample_interval_ns
                ),
            );
            return;
        }
        if let Some(n) = s.values.iter().position(|v| !v.is_finite()) {
            self.drops.record(
                Self::NAME,
                input,
                &format_args!("channel {} sample {} is {}", n / samples, n % samples, s.values[n]),
            );
            return;
        }
        if let Some(m) = &mut self.by_fix {
            m.sweep(input.stamp_ns(), (channels, s.values.to_vec()));
            return;
        }
        if self.poses.1.is_none() {
            self.before_first_pose += 1;
            return;
        }
        self.waiting
            .push_back((input.stamp_ns(), input.seq(), channels, s.values.to_vec()));
    }

    fn on_fix(&mut self, input: &Input<'_>, fix: &MapFix) -> Result<(), StageError> {
        let p = &fix.world_from_body;
        let placed = Placed {
            stamp_ns: input.stamp_ns(),
            x: p.position.x,
            y: p.position.y,
            yaw: yaw_of(&p.orientation),
        };
        if fix.locked && ![placed.x, placed.y, placed.yaw].iter().all(|v| v.is_finite()) {
            self.drops.record(
                Self::NAME,
                input,
                &"locked fix with a non-finite position or orientation",
            );
            return Ok(());
        }
        if let Some(m) = &mut self.by_fix {
            m.fix(placed.stamp_ns, fix.locked.then_some(placed));
        }
        self.place_by_fixes()
    }
}

impl Stage for LgprMapStage {
    type Params = LgprMapParams;
    const NAME: &'static str = "lgpr_map";
    const ABOUT: &'static str =
        "LGPR mapping: processed sweeps placed by the GPS/INS (or a pose source) into an on-disk map store";

    fn inputs() -> InputPorts {
        let port = |name: &str, ty: &str, optional: bool| InputSpec {
            port: PortSpec::new(name, ty),
            optional,
        };
        InputPorts::Fixed(vec![
            port("ins", Odometry::TYPE_NAME, true),
            port("pose", PoseStamped::TYPE_NAME, true),
            port("fix", MapFix::TYPE_NAME, true),
            port("sweep", Sweep::TYPE_NAME, false),
        ])
    }

    fn outputs(_: &Self::Params) -> Result<Vec<PortSpec>, ParamError> {
        Ok(Vec::new())
    }

    fn check_params(p: &Self::Params) -> Result<(), ParamError> {
        use gprflow_stage::params::{non_negative, positive};
        if p.map.as_os_str().is_empty() {
            return Err(ParamError::new("map", "must name a directory"));
        }
        p.array.check("array").map_err(to_param)?;
        positive("tile_m", p.tile_m)?;
        non_negative("min_spacing_m", p.min_spacing_m)?;
        Ok(())
    }

    fn create(params: Self::Params, ports: &Ports) -> Result<Self, StageError> {
        let sources = ["ins", "pose", "fix"]
            .iter()
            .filter(|p| ports.input(p).is_some())
            .count();
        if sources != 1 {
            return Err(StageError::failed(
                "lgpr_map: connect exactly one pose source, `ins` (GPS/INS Odometry), `pose` (PoseStamped) or `fix` (an lgpr_track's MapFix)",
            ));
        }
        Ok(Self {
            params,
            writer: None,
            poses: (None, None),
            by_fix: ports.input("fix").is_some().then(FixMatcher::default),
            waiting: VecDeque::new(),
            samples: 0,
            sample_interval_ns: 0.0,
            last_written: None,
            length_from: None,
            sweeps_written: 0,
            before_first_pose: 0,
            skipped_close: 0,
            drops: Drops::new(),
        })
    }

    fn on_message(&mut self, input: Input<'_>, _out: &mut Outputs) -> Result<(), StageError> {
        match input.name() {
            "ins" => {
                let m: Odometry = input.decode()?;
                let p = &m.pose.pose;
                let placed = Placed {
                    stamp_ns: input.stamp_ns(),
                    x: p.position.x,
                    y: p.position.y,
                    yaw: yaw_of(&p.orientation),
                };
                if [placed.x, placed.y, placed.yaw].iter().all(|v| v.is_finite()) {
                    self.on_pose(placed)?;
                } else {
                    self.drops
                        .record(Self::NAME, &input, &"non-finite position or orientation");
                }
            }
            "pose" => {
                let m: PoseStamped = input.decode()?;
                let placed = Placed {
                    stamp_ns: input.stamp_ns(),
                    x: m.pose.position.x,
                    y: m.pose.position.y,
                    yaw: yaw_of(&m.pose.orientation),
                };
                if [placed.x, placed.y, placed.yaw].iter().all(|v| v.is_finite()) {
                    self.on_pose(placed)?;
                } else {
                    self.drops
                        .record(Self::NAME, &input, &"non-finite position or orientation");
                }
            }
            "fix" => {
                let m: MapFix = input.decode()?;
                self.on_fix(&input, &m)?;
            }
            "sweep" => {
                let s: Sweep = input.decode()?;
                self.on_sweep(&input, &s);
                self.place_by_fixes()?;
            }
            _ => {}
        }
        Ok(())
    }

    fn finish(&mut self, _out: &mut Outputs) -> Result<(), StageError> {
        let after_last_pose = self.waiting.len();
        self.waiting.clear();
        self.drops.report(Self::NAME);
        if let Some(m) = &mut self.by_fix {
            m.finish();
            tracing::info!(
                placed = self.sweeps_written,
                unlocked = m.unlocked,
                without_fix = m.no_fix,
                "lgpr_map: sweeps placed by their locked map fixes; the others left out"
            );
        } else if self.before_first_pose + after_last_pose as u64 > 0 {
            tracing::warn!(
                before_first_pose = self.before_first_pose,
                after_last_pose,
                "lgpr_map: sweeps outside the poses' time span could not be placed"
            );
        }
        let Some(mut writer) = self.writer.take() else {
            tracing::warn!(map = %self.params.map.display(), "lgpr_map: no sweep placed; nothing written");
            return Ok(());
        };
        if let (Some(from), Some(last)) = (self.length_from, self.last_written) {
            writer.add_length((last.0 - from.0).hypot(last.1 - from.1));
        }
        let dir = self.params.map.clone();
        let info = writer.finish().map_err(StageError::failed)?;
        let bytes = crate::map::MapReader::open(&dir)
            .and_then(|r| r.tiles())
            .map(|t| t.values().sum::<u64>())
            .map_err(StageError::failed)?;
        let km = info.length_m / 1000.0;
        tracing::info!(
            map = %dir.display(),
            sweeps = self.sweeps_written,
            skipped_close = self.skipped_close,
            columns = info.columns,
            length_m = format!("{:.1}", info.length_m),
            bytes,
            mb_per_km = format!("{:.1}", if km > 0.0 { bytes as f64 / 1e6 / km } else { 0.0 }),
            passes = info.passes,
            "lgpr_map: map written"
        );
        Ok(())
    }
}

/// A library parameter error as the stage reports it.
pub(crate) fn to_param(e: crate::Error) -> ParamError {
    match e {
        crate::Error::Param(p) => p,
        other => ParamError::new("", other.to_string()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn at(stamp_ns: i64) -> Placed {
        Placed {
            stamp_ns,
            x: stamp_ns as f64,
            y: 1.0,
            yaw: 0.0,
        }
    }

    #[test]
    fn sweeps_pair_with_the_fix_of_their_stamp_in_either_order_and_the_others_are_counted() {
        let mut m = FixMatcher::default();
        // fix before its sweep, sweep before its fix
        m.fix(10, Some(at(10)));
        assert!(m.next_placed().is_none());
        m.sweep(10, "a");
        m.sweep(20, "b");
        assert_eq!(m.next_placed().map(|(p, s)| (p.x, s)), Some((10.0, "a")));
        assert!(m.next_placed().is_none());
        m.fix(20, Some(at(20)));
        assert_eq!(m.next_placed().map(|(p, s)| (p.x, s)), Some((20.0, "b")));
        // an unlocked fix leaves its sweep out; a sweep the fixes skipped got none; a fix whose
        // sweep never came is let go; a fix out of order is ignored
        m.sweep(30, "unlocked");
        m.sweep(40, "skipped");
        m.sweep(60, "c");
        m.fix(30, None);
        m.fix(25, Some(at(25)));
        m.fix(50, Some(at(50)));
        m.fix(60, Some(at(60)));
        assert_eq!(m.next_placed().map(|(p, s)| (p.x, s)), Some((60.0, "c")));
        assert_eq!((m.unlocked, m.no_fix), (1, 1));
        m.sweep(70, "last");
        m.finish();
        assert_eq!((m.unlocked, m.no_fix), (1, 2));
        assert!(m.next_placed().is_none());
    }
}

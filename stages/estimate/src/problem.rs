//! The synthetic benchmark problem (`tools/peer/gtsam_problem.py N -o FILE`, which GTSAM
//! solves in `tools/peer/gtsam_solve.py`) and the graph it describes.
//!
//! Format, one record per line, whitespace separated:
//! `PARAMS N imu_per_state imu_dt g acc_nd gyr_nd acc_rw gyr_rw odo_sig[6] lc_sig[6]`,
//! `GT i x y z qx qy qz qw vx vy vz`, `ODO i-1 i x y z qx qy qz qw`, `IMU i ax ay az gx gy gz`,
//! `LC j i x y z qx qy qz qw`, `LINEMAP k rho theta rho0 theta0`, `LINE i k z`.
//! Priors as the peer: pose sigma 1e-3, velocity 0.01, bias 0.1; loop closures under Huber 1.345;
//! line measurements sigma 0.05 m.

use std::path::Path;

use nalgebra::Vector3;

use crate::factors::{BetweenPose, KnownLineDistance, LineDistance, PosePrior, VectorPrior};
use crate::graph::FactorGraph;
use crate::imu::{CombinedImuFactor, ImuParams, ImuPreintegration, NavKeys};
use crate::lie::Pose3;
use crate::noise::{NoiseModel, RobustKernel};
use crate::values::{HoughLine, ImuBias, Values, VarId, Variable};
use crate::{Error, Result};

/// Pose prior sigma on the first state (rad and m).
pub const PRIOR_POSE_SIGMA: f64 = 1e-3;
/// Velocity prior sigma on the first state, m/s.
pub const PRIOR_VELOCITY_SIGMA_MPS: f64 = 0.01;
/// Bias prior sigma on the first state.
pub const PRIOR_BIAS_SIGMA: f64 = 0.1;
/// Huber threshold of the loop closures (whitened).
pub const LOOP_CLOSURE_HUBER_K: f64 = 1.345;
/// Line measurement sigma, m.
pub const LINE_SIGMA_M: f64 = 0.05;
/// Prior sigma on an estimated line's `(rho, theta)`.
pub const LINE_PRIOR_SIGMA: f64 = 0.2;

/// The `PARAMS` record.
#[derive(Debug, Clone, PartialEq)]
pub struct ProblemParams {
    /// Number of states.
    pub states: usize,
    /// IMU samples between consecutive states.
    pub imu_per_state: usize,
    /// IMU sample interval, s.
    pub imu_dt_s: f64,
    /// IMU noise model and gravity.
    pub imu: ImuParams,
    /// Odometry sigmas `[rot x3, trans x3]`.
    pub odometry_sigmas: [f64; 6],
    /// Loop-closure sigmas `[rot x3, trans x3]`.
    pub loop_closure_sigmas: [f64; 6],
}

/// True state.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GroundTruth {
    /// Pose.
    pub pose: Pose3,
    /// Velocity in the world, m/s.
    pub velocity_mps: Vector3<f64>,
}

/// A relative pose measurement `from_from_to`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RelativePose {
    /// Earlier state.
    pub from: usize,
    /// Later state.
    pub to: usize,
    /// `from^-1 to`.
    pub measured: Pose3,
}

/// One map line: the truth and the noisy initial guess.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MapLine {
    /// True line.
    pub truth: HoughLine,
    /// Initial guess.
    pub initial: HoughLine,
}

/// One line observation.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LineObservation {
    /// Observing state.
    pub state: usize,
    /// Line index.
    pub line: usize,
    /// Forward distance, m.
    pub distance_m: f64,
}

/// A whole exported problem.
#[derive(Debug, Clone, PartialEq)]
pub struct Problem {
    /// The `PARAMS` record.
    pub params: ProblemParams,
    /// Ground truth per state.
    pub ground_truth: Vec<GroundTruth>,
    /// Odometry into state `i` at index `i` (`None` for state 0).
    pub odometry: Vec<Option<RelativePose>>,
    /// IMU samples `[ax ay az gx gy gz]` integrated into state `i`, at index `i`.
    pub imu: Vec<Vec<[f64; 6]>>,
    /// Loop closures.
    pub loop_closures: Vec<RelativePose>,
    /// Map lines.
    pub lines: Vec<MapLine>,
    /// Line observations.
    pub line_observations: Vec<LineObservation>,
}

struct Fields<'a> {
    path: &'a str,
    line: usize,
    it: std::str::SplitWhitespace<'a>,
}

impl Fields<'_> {
    fn err(&self, message: impl Into<String>) -> Error {
        Error::Parse {
            path: self.path.to_owned(),
            line: self.line,
            message: message.into(),
        }
    }
    fn f64(&mut self, what: &str) -> Result<f64> {
        let tok = self.it.next().ok_or_else(|| self.err(format!("missing {what}")))?;
        let v: f64 = tok
            .parse()
            .map_err(|_| self.err(format!("{what}: `{tok}` is not a number")))?;
        if v.is_finite() {
            Ok(v)
        } else {
            Err(self.err(format!("{what}: `{tok}` is not finite")))
        }
    }
    fn index(&mut self, what: &str, bound: usize) -> Result<usize> {
        let tok = self.it.next().ok_or_else(|| self.err(format!("missing {what}")))?;
        let v: usize = tok
            .parse()
            .map_err(|_| self.err(format!("{what}: `{tok}` is not an index")))?;
        if v < bound {
            Ok(v)
        } else {
            Err(self.err(format!("{what} {v} out of range (< {bound})")))
        }
    }
    fn pose(&mut self) -> Result<Pose3> {
        let t = Vector3::new(self.f64("x")?, self.f64("y")?, self.f64("z")?);
        let q = [self.f64("qx")?, self.f64("qy")?, self.f64("qz")?, self.f64("qw")?];
        let n = q.iter().map(|c| c * c).sum::<f64>().sqrt();
        if (n - 1.0).abs() > 1e-6 {
            return Err(self.err(format!("quaternion norm {n} is not 1")));
        }
        Ok(Pose3::from_quaternion(q, t))
    }
    fn end(&mut self) -> Result<()> {
        match self.it.next() {
            None => Ok(()),
            Some(t) => Err(self.err(format!("unexpected trailing field `{t}`"))),
        }
    }
}

impl Problem {
    /// Reads an exported problem file.
    ///
    /// # Errors
    /// [`Error::Io`], or [`Error::Parse`] with the line number of the first bad record.
    pub fn read(path: &Path) -> Result<Self> {
        let name = path.display().to_string();
        let text = std::fs::read_to_string(path).map_err(|source| Error::Io {
            path: name.clone(),
            source,
        })?;
        Self::parse(&text, &name)
    }

    /// Parses the text of an exported problem (`path` names it in errors).
    ///
    /// # Errors
    /// [`Error::Parse`] with the line number of the first bad record.
    pub fn parse(text: &str, path: &str) -> Result<Self> {
        let mut params: Option<ProblemParams> = None;
        let mut gt: Vec<Option<GroundTruth>> = Vec::new();
        let mut odometry = Vec::new();
        let mut imu: Vec<Vec<[f64; 6]>> = Vec::new();
        let mut loop_closures = Vec::new();
        let mut lines: Vec<Option<MapLine>> = Vec::new();
        let mut line_obs = Vec::new();
        for (k, raw) in text.lines().enumerate() {
            let mut it = raw.split_whitespace();
            let Some(tag) = it.next() else { continue };
            let mut f = Fields { path, line: k + 1, it };
            if tag.starts_with('#') {
                continue;
            }
            if tag != "PARAMS" && params.is_none() {
                return Err(f.err("the first record must be PARAMS"));
            }
            let n = params.as_ref().map_or(0, |p| p.states);
            match tag {
                "PARAMS" => {
                    if params.is_some() {
                        return Err(f.err("second PARAMS record"));
                    }
                    let states = f.index("N", usize::MAX)?;
                    let imu_per_state = f.index("imu_per_state", usize::MAX)?;
                    let imu_dt_s = f.f64("imu_dt")?;
                    let g = f.f64("g")?;
                    let imu_p = ImuParams {
                        gravity_mps2: Vector3::new(0.0, 0.0, -g),
                        acc_noise_density: f.f64("acc_nd")?,
                        gyro_noise_density: f.f64("gyr_nd")?,
                        acc_bias_random_walk: f.f64("acc_rw")?,
                        gyro_bias_random_walk: f.f64("gyr_rw")?,
                        integration_variance: 1e-8,
                    };
                    let mut odo = [0.0; 6];
                    for s in &mut odo {
                        *s = f.f64("odo_sig")?;
                    }
                    let mut lc = [0.0; 6];
                    for s in &mut lc {
                        *s = f.f64("lc_sig")?;
                    }
                    f.end()?;
                    if states == 0 || imu_per_state == 0 || imu_dt_s <= 0.0 {
                        return Err(f.err("N, imu_per_state and imu_dt must be positive"));
                    }
                    gt = vec![None; states];
                    odometry = vec![None; states];
                    imu = vec![Vec::new(); states];
                    params = Some(ProblemParams {
                        states,
                        imu_per_state,
                        imu_dt_s,
                        imu: imu_p,
                        odometry_sigmas: odo,
                        loop_closure_sigmas: lc,
                    });
                }
                "GT" => {
                    let i = f.index("state", n)?;
                    let pose = f.pose()?;
                    let v = Vector3::new(f.f64("vx")?, f.f64("vy")?, f.f64("vz")?);
                    f.end()?;
                    gt[i] = Some(GroundTruth { pose, velocity_mps: v });
                }
                "ODO" | "LC" => {
                    let from = f.index("from state", n)?;
                    let to = f.index("to state", n)?;
                    let measured = f.pose()?;
                    f.end()?;
                    let rel = RelativePose { from, to, measured };
                    if tag == "ODO" {
                        if to != from + 1 {
                            return Err(f.err("ODO must join consecutive states"));
                        }
                        odometry[to] = Some(rel);
                    } else {
                        loop_closures.push(rel);
                    }
                }
                "IMU" => {
                    let i = f.index("state", n)?;
                    if i == 0 {
                        return Err(f.err("IMU samples integrate into states 1.."));
                    }
                    let mut s = [0.0; 6];
                    for (c, name) in s.iter_mut().zip(["ax", "ay", "az", "gx", "gy", "gz"]) {
                        *c = f.f64(name)?;
                    }
                    f.end()?;
                    imu[i].push(s);
                }
                "LINEMAP" => {
                    let k = f.index("line", usize::MAX)?;
                    let truth = HoughLine {
                        rho_m: f.f64("rho")?,
                        theta_rad: f.f64("theta")?,
                    };
                    let initial = HoughLine {
                        rho_m: f.f64("rho0")?,
                        theta_rad: f.f64("theta0")?,
                    };
                    f.end()?;
                    if lines.len() <= k {
                        lines.resize(k + 1, None);
                    }
                    lines[k] = Some(MapLine { truth, initial });
                }
                "LINE" => {
                    let state = f.index("state", n)?;
                    let line = f.index("line", usize::MAX)?;
                    let distance_m = f.f64("z")?;
                    f.end()?;
                    line_obs.push(LineObservation {
                        state,
                        line,
                        distance_m,
                    });
                }
                other => return Err(f.err(format!("unknown record `{other}`"))),
            }
        }
        let whole = |message: String| Error::Parse {
            path: path.to_owned(),
            line: 0,
            message,
        };
        let params = params.ok_or_else(|| whole("no PARAMS record".into()))?;
        let ground_truth = gt
            .into_iter()
            .enumerate()
            .map(|(i, g)| g.ok_or_else(|| whole(format!("no GT record for state {i}"))))
            .collect::<Result<Vec<_>>>()?;
        for i in 1..params.states {
            if odometry[i].is_none() {
                return Err(whole(format!("no ODO record into state {i}")));
            }
            if imu[i].len() != params.imu_per_state {
                return Err(whole(format!(
                    "state {i} has {} IMU samples, PARAMS says {}",
                    imu[i].len(),
                    params.imu_per_state
                )));
            }
        }
        let lines = lines
            .into_iter()
            .enumerate()
            .map(|(k, l)| l.ok_or_else(|| whole(format!("no LINEMAP record for line {k}"))))
            .collect::<Result<Vec<_>>>()?;
        if let Some(o) = line_obs.iter().find(|o| o.line >= lines.len()) {
            return Err(whole(format!(
                "LINE of state {} refers to unknown line {}",
                o.state, o.line
            )));
        }
        Ok(Self {
            params,
            ground_truth,
            odometry,
            imu,
            loop_closures,
            lines,
            line_observations: line_obs,
        })
    }

    /// Time between states, s.
    #[must_use]
    pub fn state_dt_s(&self) -> f64 {
        self.params.imu_dt_s * self.params.imu_per_state as f64
    }

    /// The dead-reckoning initial guess of the peer: odometry composed from the true first pose,
    /// finite-difference velocities, zero biases.
    #[must_use]
    pub fn dead_reckoning(&self) -> Vec<(Pose3, Vector3<f64>)> {
        let n = self.params.states;
        let mut poses = vec![self.ground_truth[0].pose];
        for i in 1..n {
            let step = self.odometry[i].map_or(Pose3::identity(), |o| o.measured);
            poses.push(poses[i - 1].compose(&step));
        }
        let dt = self.state_dt_s();
        (0..n)
            .map(|i| {
                let (a, b) = if i + 1 < n {
                    (i, i + 1)
                } else {
                    (i.saturating_sub(1), i)
                };
                let v = if a == b {
                    Vector3::zeros()
                } else {
                    (poses[b].trans_m - poses[a].trans_m) / dt
                };
                (poses[i], v)
            })
            .collect()
    }

    /// Preintegrates the IMU samples into state `i` (>= 1) with bias estimate `bias_hat`.
    ///
    /// # Errors
    /// A bad sample interval.
    pub fn preintegrate(&self, i: usize, bias_hat: ImuBias) -> Result<ImuPreintegration> {
        let mut pim = ImuPreintegration::new(self.params.imu, bias_hat);
        for s in &self.imu[i] {
            pim.integrate(
                &Vector3::new(s[0], s[1], s[2]),
                &Vector3::new(s[3], s[4], s[5]),
                self.params.imu_dt_s,
            )?;
        }
        Ok(pim)
    }
}

/// How line observations enter the graph.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum LineMode {
    /// Not at all.
    #[default]
    Off,
    /// Against the true map lines (the peer's `--fixed-lines`).
    Known,
    /// Lines are variables with a prior at their initial guess.
    Estimated,
}

/// Builds the graph of a [`Problem`] state by state; the batch and incremental runs share it.
#[derive(Debug)]
pub struct ProblemGraph {
    /// The factors so far.
    pub graph: FactorGraph,
    /// The current values.
    pub values: Values,
    /// Variables of each state added so far.
    pub states: Vec<NavKeys>,
    /// Line variables (estimated mode).
    pub line_vars: Vec<VarId>,
    mode: LineMode,
    odo_noise: NoiseModel,
    lc_noise: NoiseModel,
    line_noise: NoiseModel,
}

impl ProblemGraph {
    /// An empty graph for `problem`; in [`LineMode::Estimated`] the line variables and their
    /// priors are added at once.
    ///
    /// # Errors
    /// Bad sigmas in the problem.
    pub fn new(problem: &Problem, mode: LineMode) -> Result<Self> {
        let mut pg = Self {
            graph: FactorGraph::new(),
            values: Values::new(),
            states: Vec::new(),
            line_vars: Vec::new(),
            mode,
            odo_noise: NoiseModel::diagonal(&problem.params.odometry_sigmas)?,
            lc_noise: NoiseModel::diagonal(&problem.params.loop_closure_sigmas)?.robust(RobustKernel::Huber {
                k: LOOP_CLOSURE_HUBER_K,
            }),
            line_noise: NoiseModel::isotropic(1, LINE_SIGMA_M)?,
        };
        if mode == LineMode::Estimated {
            for l in &problem.lines {
                let id = pg.values.push(Variable::Line(l.initial));
                pg.graph.add(VectorPrior::line(
                    id,
                    l.initial,
                    NoiseModel::isotropic(2, LINE_PRIOR_SIGMA)?,
                )?);
                pg.line_vars.push(id);
            }
        }
        Ok(pg)
    }

    /// Adds state `i` (the next one) with initial value `(pose, velocity, bias)` and every
    /// factor that ends at it; `bias_hat` is the preintegration's bias estimate.
    ///
    /// # Errors
    /// States out of order, or a bad measurement.
    pub fn add_state(
        &mut self,
        problem: &Problem,
        i: usize,
        init: (Pose3, Vector3<f64>, ImuBias),
        bias_hat: ImuBias,
    ) -> Result<Vec<usize>> {
        if i != self.states.len() || i >= problem.params.states {
            return Err(Error::BadMeasurement(format!("state {i} added out of order")));
        }
        let keys = NavKeys {
            pose: self.values.push(Variable::Pose(init.0)),
            velocity: self.values.push(Variable::Velocity(init.1)),
            bias: self.values.push(Variable::Bias(init.2)),
        };
        self.states.push(keys);
        let first = self.graph.len();
        if i == 0 {
            let gt = problem.ground_truth[0];
            self.graph.add(PosePrior::new(
                keys.pose,
                gt.pose,
                NoiseModel::isotropic(6, PRIOR_POSE_SIGMA)?,
            )?);
            self.graph.add(VectorPrior::velocity(
                keys.velocity,
                gt.velocity_mps,
                NoiseModel::isotropic(3, PRIOR_VELOCITY_SIGMA_MPS)?,
            )?);
            self.graph.add(VectorPrior::bias(
                keys.bias,
                ImuBias::default(),
                NoiseModel::isotropic(6, PRIOR_BIAS_SIGMA)?,
            )?);
        } else {
            let prev = self.states[i - 1];
            self.graph
                .add(CombinedImuFactor::new(prev, keys, problem.preintegrate(i, bias_hat)?)?);
            if let Some(o) = problem.odometry[i] {
                self.graph.add(BetweenPose::new(
                    prev.pose,
                    keys.pose,
                    o.measured,
                    self.odo_noise.clone(),
                )?);
            }
            for lc in problem.loop_closures.iter().filter(|lc| lc.to == i && lc.from < i) {
                let from = self.states[lc.from].pose;
                self.graph
                    .add(BetweenPose::new(from, keys.pose, lc.measured, self.lc_noise.clone())?);
            }
        }
        for obs in problem.line_observations.iter().filter(|o| o.state == i) {
            match self.mode {
                LineMode::Off => {}
                LineMode::Known => {
                    let line = problem.lines[obs.line].truth;
                    self.graph.add(KnownLineDistance::new(
                        keys.pose,
                        line,
                        obs.distance_m,
                        self.line_noise.clone(),
                    )?);
                }
                LineMode::Estimated => {
                    let l = self.line_vars[obs.line];
                    self.graph.add(LineDistance::new(
                        keys.pose,
                        l,
                        obs.distance_m,
                        self.line_noise.clone(),
                    )?);
                }
            }
        }
        Ok((first..self.graph.len()).collect())
    }

    /// The whole graph at the peer's dead-reckoning initial guess (preintegrated at zero bias).
    ///
    /// # Errors
    /// As [`ProblemGraph::add_state`].
    pub fn batch(problem: &Problem, mode: LineMode) -> Result<Self> {
        let mut pg = Self::new(problem, mode)?;
        for (i, (pose, vel)) in problem.dead_reckoning().into_iter().enumerate() {
            pg.add_state(problem, i, (pose, vel, ImuBias::default()), ImuBias::default())?;
        }
        Ok(pg)
    }

    /// Absolute trajectory error against the ground truth, no alignment: `(rmse_m, max_m)`.
    ///
    /// # Errors
    /// Missing pose variables.
    pub fn ate(&self, problem: &Problem) -> Result<(f64, f64)> {
        let mut sum = 0.0;
        let mut max: f64 = 0.0;
        for (k, gt) in self.states.iter().zip(&problem.ground_truth) {
            let e = (self.values.pose(k.pose)?.trans_m - gt.pose.trans_m).norm();
            sum += e * e;
            max = max.max(e);
        }
        Ok(((sum / self.states.len().max(1) as f64).sqrt(), max))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const TINY: &str =
        "PARAMS 2 2 0.05 9.81 0.01 0.001 0.001 0.0001 0.005 0.005 0.005 0.02 0.02 0.02 0.01 0.01 0.01 0.05 0.05 0.05
GT 0 0 0 0 0 0 0 1 1 0 0
GT 1 0.1 0 0 0 0 0 1 1 0 0
ODO 0 1 0.1 0 0 0 0 0 1
IMU 1 0 0 9.81 0 0 0
IMU 1 0 0 9.81 0 0 0
LINEMAP 0 25 0 25.1 0.01
LINE 1 0 24.9
";

    #[test]
    fn parses_and_builds_a_tiny_problem() {
        let p = Problem::parse(TINY, "tiny").expect("parse");
        assert_eq!(p.params.states, 2);
        for mode in [LineMode::Off, LineMode::Known, LineMode::Estimated] {
            let pg = ProblemGraph::batch(&p, mode).expect("graph");
            let e = pg.graph.error(&pg.values).expect("error");
            assert!(e.is_finite());
        }
        let pg = ProblemGraph::batch(&p, LineMode::Off).expect("graph");
        let (rmse, _) = pg.ate(&p).expect("ate");
        assert!(rmse < 1e-9);
    }

    #[test]
    fn errors_name_the_line() {
        let bad = TINY.replace("IMU 1 0 0 9.81 0 0 0\nIMU", "IMU 1 0 0 x 0 0 0\nIMU");
        let e = Problem::parse(&bad, "p.txt").expect_err("bad number");
        assert!(e.to_string().starts_with("p.txt:5: az"), "{e}");
        let e = Problem::parse("GT 0 0 0 0 0 0 0 1 0 0 0", "p.txt").expect_err("no params");
        assert!(e.to_string().contains("p.txt:1:"), "{e}");
        let e = Problem::parse(&TINY.replace("ODO 0 1", "ODO 0 7"), "p.txt").expect_err("range");
        assert!(e.to_string().contains("p.txt:4: to state 7 out of range"), "{e}");
    }

    #[test]
    fn never_panics_on_garbage() {
        for text in [
            "",
            "PARAMS",
            "PARAMS 1 1 1 1",
            "\u{0}\u{1}",
            "PARAMS -1 2 3",
            "LINE 1 2 3",
            &TINY[..200],
        ] {
            let _ = Problem::parse(text, "g");
        }
    }
}

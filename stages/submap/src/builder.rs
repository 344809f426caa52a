//! [`SubmapBuilder`]: traces, wheel distances and IMU rates in, submaps out.

use std::collections::VecDeque;

use gprflow_geometry::Planar;

use crate::odometry::PlanarOdometry;
use crate::{Error, Result, SubmapParams, rubber_band, saliency};

/// One submap (see the crate docs for the conventions).
#[derive(Debug, Clone, PartialEq)]
pub struct Submap {
    /// Sequence number among the submaps this builder produced (valid or not).
    pub id: u32,
    /// Stamp of the oldest trace, ns.
    pub start_stamp_ns: i64,
    /// Stamp of the newest trace, ns.
    pub end_stamp_ns: i64,
    /// Wheel distance at the centre of column 0, m.
    pub start_distance_m: f64,
    /// Wheel distance at the centre of the last column, m.
    pub end_distance_m: f64,
    /// Along-track size of a column, m.
    pub resolution_m: f64,
    /// Samples per column.
    pub rows: usize,
    /// Columns.
    pub cols: usize,
    /// Odometry pose at the oldest trace.
    pub start_pose: Planar,
    /// Odometry pose at the newest trace.
    pub end_pose: Planar,
    /// [`saliency`] of the pixels.
    pub saliency: f32,
    /// The validity rule held.
    pub valid: bool,
    /// Why the rule failed (empty when valid).
    pub invalid_reason: String,
    /// Columns that held at least one trace (the others are interpolated).
    pub filled_cols: usize,
    /// `rows x cols`, row-major.
    pub pixels: Vec<f32>,
    /// When the rig was over each column's centre, ns: interpolated along travel between
    /// the bins' mean stamps (`column_stamps`), extended past the ends along the first and last pieces.
    pub column_stamps_ns: Vec<i64>,
}

/// Counts over a builder's life.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct SubmapStats {
    /// Traces placed in a column.
    pub traces: u64,
    /// Submaps that passed the validity rule.
    pub valid: u64,
    /// Submaps that failed it.
    pub invalid: u64,
    /// Traces received before any wheel distance and never placed.
    pub traces_without_wheel: u64,
}

/// One along-track bin of `resolution_m` of travel.
#[derive(Debug, Clone)]
struct Bin {
    /// `floor(travel / resolution)`.
    index: i64,
    sum: Vec<f32>,
    count: u32,
    first_stamp_ns: i64,
    last_stamp_ns: i64,
    /// Sum of its traces' stamps, ns (for their mean).
    stamp_sum_ns: i128,
    /// Sums of the wheel distance and travel of its traces (for their means).
    distance_sum_m: f64,
    travel_sum_m: f64,
    /// Motion segment (increments at every reversal of the encoder).
    segment: u64,
    /// Direction of the segment: +1 forward, -1 backward, 0 not yet moving.
    direction: i8,
    first_pose: Planar,
    last_pose: Planar,
}

/// A wheel sample with the travel and pose at it.
#[derive(Debug, Clone, Copy)]
struct WheelSample {
    stamp_ns: i64,
    distance_m: f64,
    travel_m: f64,
    segment: u64,
    direction: i8,
    pose: Planar,
}

/// Builds submaps from traces, wheel distances and IMU rates delivered in stamp order.
///
/// A trace waits until a wheel sample at or after its stamp arrives, then takes the distance
/// interpolated between the two wheel samples around it.
#[derive(Debug)]
pub struct SubmapBuilder {
    params: SubmapParams,
    cols: usize,
    rows: Option<usize>,
    odometry: PlanarOdometry,
    last_wheel: Option<WheelSample>,
    travel_m: f64,
    segment: u64,
    direction: i8,
    pending: VecDeque<(i64, Vec<f32>)>,
    bins: VecDeque<Bin>,
    /// (stamp, |gyro z|, |accel y|)
    imu: VecDeque<(i64, f64, f64)>,
    last_imu_ns: Option<i64>,
    last_trace_ns: Option<i64>,
    next_emit_travel_m: f64,
    next_id: u32,
    stats: SubmapStats,
}

/// Traces waiting for a wheel sample beyond this are an upstream fault: the oldest are placed
/// with the last known distance.
const MAX_PENDING_TRACES: usize = 10_000;

impl SubmapBuilder {
    /// A builder with checked parameters.
    ///
    /// # Errors
    /// [`Error::Param`] naming the bad field.
    pub fn new(params: SubmapParams) -> Result<Self> {
        params.check()?;
        Ok(Self {
            cols: params.cols(),
            next_emit_travel_m: params.length_m,
            params,
            rows: None,
            odometry: PlanarOdometry::new(),
            last_wheel: None,
            travel_m: 0.0,
            segment: 0,
            direction: 0,
            pending: VecDeque::new(),
            bins: VecDeque::new(),
            imu: VecDeque::new(),
            last_imu_ns: None,
            last_trace_ns: None,
            next_id: 0,
            stats: SubmapStats::default(),
        })
    }

    /// Counts so far.
    pub fn stats(&self) -> SubmapStats {
        self.stats
    }

    /// Columns of every submap.
    pub fn cols(&self) -> usize {
        self.cols
    }

    /// An IMU sample: z gyro rate (rad/s) and y acceleration (m/s^2) in the body frame.
    ///
    /// # Errors
    /// [`Error::BadMeasurement`] for non-finite values or a stamp before the previous one
    /// (the sample is not used).
    pub fn imu(&mut self, stamp_ns: i64, gyro_z_radps: f64, accel_y_mps2: f64) -> Result<()> {
        if !(gyro_z_radps.is_finite() && accel_y_mps2.is_finite()) {
            return Err(Error::BadMeasurement(format!(
                "imu at {stamp_ns} ns: non-finite gyro z {gyro_z_radps} / accel y {accel_y_mps2}"
            )));
        }
        if let Some(last) = self.last_imu_ns
            && stamp_ns < last
        {
            return Err(Error::BadMeasurement(format!(
                "imu at {stamp_ns} ns: stamp before the previous one ({last} ns)"
            )));
        }
        self.last_imu_ns = Some(stamp_ns);
        self.odometry.gyro(stamp_ns, gyro_z_radps);
        self.imu.push_back((stamp_ns, gyro_z_radps.abs(), accel_y_mps2.abs()));
        Ok(())
    }

    /// A cumulative signed wheel distance, m. Places the traces waiting for it and returns
    /// the submaps that became due.
    ///
    /// # Errors
    /// [`Error::BadMeasurement`] for a non-finite distance or a stamp before the previous one.
    pub fn wheel(&mut self, stamp_ns: i64, distance_m: f64) -> Result<Vec<Submap>> {
        if !distance_m.is_finite() {
            return Err(Error::BadMeasurement(format!(
                "wheel at {stamp_ns} ns: non-finite distance {distance_m}"
            )));
        }
        if let Some(last) = &self.last_wheel
            && stamp_ns < last.stamp_ns
        {
            return Err(Error::BadMeasurement(format!(
                "wheel at {stamp_ns} ns: stamp before the previous one ({} ns)",
                last.stamp_ns
            )));
        }
        if let Some(last) = &self.last_wheel {
            let step = distance_m - last.distance_m;
            let dir: i8 = if step > 0.0 {
                1
            } else if step < 0.0 {
                -1
            } else {
                0
            };
            if dir != 0 && dir != self.direction {
                if self.direction != 0 {
                    self.segment += 1;
                }
                self.direction = dir;
            }
            self.travel_m += step.abs();
        }
        self.odometry.wheel(distance_m);
        let sample = WheelSample {
            stamp_ns,
            distance_m,
            travel_m: self.travel_m,
            segment: self.segment,
            direction: self.direction,
            pose: self.odometry.pose(),
        };
        let previous = self.last_wheel.replace(sample);
        let mut out = Vec::new();
        while let Some((t, _)) = self.pending.front() {
            if *t > stamp_ns {
                break;
            }
            let Some((t, samples)) = self.pending.pop_front() else {
                break;
            };
            let at = interpolate(previous.as_ref(), &sample, t);
            self.place(t, samples, &at, &mut out);
        }
        Ok(out)
    }

    /// A processed trace. Returns the submaps that became due (usually none: the trace waits
    /// for the next wheel sample).
    ///
    /// # Errors
    /// [`Error::BadMeasurement`] for non-finite samples, a length different from the first
    /// trace's, or a stamp before the previous trace's (the trace is not used).
    pub fn trace(&mut self, stamp_ns: i64, samples: &[f32]) -> Result<Vec<Submap>> {
        if let Some(i) = samples.iter().position(|v| !v.is_finite()) {
            return Err(Error::BadMeasurement(format!(
                "trace at {stamp_ns} ns: sample {i} is not finite ({})",
                samples[i]
            )));
        }
        if samples.is_empty() {
            return Err(Error::BadMeasurement(format!("trace at {stamp_ns} ns: no samples")));
        }
        match self.rows {
            Some(rows) if rows != samples.len() => {
                return Err(Error::BadMeasurement(format!(
                    "trace at {stamp_ns} ns: {} samples, the first trace had {rows}",
                    samples.len()
                )));
            }
            Some(_) => {}
            None => self.rows = Some(samples.len()),
        }
        if let Some(last) = self.last_trace_ns
            && stamp_ns < last
        {
            return Err(Error::BadMeasurement(format!(
                "trace at {stamp_ns} ns: stamp before the previous trace ({last} ns)"
            )));
        }
        self.last_trace_ns = Some(stamp_ns);
        let mut out = Vec::new();
        match self.last_wheel {
            Some(w) if stamp_ns <= w.stamp_ns => {
                // the wheel is already past it (traces delayed by upstream processing)
                let at = WheelSample { stamp_ns, ..w };
                self.place(stamp_ns, samples.to_vec(), &at, &mut out);
            }
            _ => {
                self.pending.push_back((stamp_ns, samples.to_vec()));
                if self.pending.len() > MAX_PENDING_TRACES
                    && let (Some(w), Some((t, s))) = (self.last_wheel, self.pending.pop_front())
                {
                    let at = WheelSample { stamp_ns: t, ..w };
                    self.place(t, s, &at, &mut out);
                }
            }
        }
        Ok(out)
    }

    /// End of the inputs: places waiting traces at the last wheel distance and returns any
    /// submap that became due. Traces that never saw a wheel sample are counted in
    /// [`SubmapStats::traces_without_wheel`].
    pub fn finish(&mut self) -> Vec<Submap> {
        let mut out = Vec::new();
        while let Some((t, s)) = self.pending.pop_front() {
            match self.last_wheel {
                Some(w) => {
                    let at = WheelSample { stamp_ns: t, ..w };
                    self.place(t, s, &at, &mut out);
                }
                None => self.stats.traces_without_wheel += 1,
            }
        }
        out
    }

    fn place(&mut self, stamp_ns: i64, samples: Vec<f32>, at: &WheelSample, out: &mut Vec<Submap>) {
        let res = self.params.resolution_m;
        let index = (at.travel_m / res).floor() as i64;
        self.stats.traces += 1;
        match self.bins.back_mut() {
            Some(bin) if bin.index == index && bin.segment == at.segment => {
                for (s, v) in bin.sum.iter_mut().zip(&samples) {
                    *s += *v;
                }
                bin.count += 1;
                bin.last_stamp_ns = stamp_ns;
                bin.stamp_sum_ns += i128::from(stamp_ns);
                bin.distance_sum_m += at.distance_m;
                bin.travel_sum_m += at.travel_m;
                bin.last_pose = at.pose;
                if bin.direction == 0 {
                    bin.direction = at.direction;
                }
            }
            _ => self.bins.push_back(Bin {
                index,
                sum: samples,
                count: 1,
                first_stamp_ns: stamp_ns,
                last_stamp_ns: stamp_ns,
                stamp_sum_ns: i128::from(stamp_ns),
                distance_sum_m: at.distance_m,
                travel_sum_m: at.travel_m,
                segment: at.segment,
                direction: at.direction,
                first_pose: at.pose,
                last_pose: at.pose,
            }),
        }
        let first_kept = index - self.cols as i64 + 1;
        while self.bins.front().is_some_and(|b| b.index < first_kept) {
            self.bins.pop_front();
        }
        if at.travel_m + 1e-12 >= self.next_emit_travel_m {
            while self.next_emit_travel_m <= at.travel_m + 1e-12 {
                self.next_emit_travel_m += self.params.spacing_m;
            }
            if let Some(s) = self.assemble(first_kept) {
                out.push(s);
            }
        }
        if let Some(oldest) = self.bins.front().map(|b| b.first_stamp_ns) {
            while self.imu.front().is_some_and(|s| s.0 < oldest) {
                self.imu.pop_front();
            }
        }
    }

    /// The submap over bins `first_index ..first_index + cols`.
    fn assemble(&mut self, first_index: i64) -> Option<Submap> {
        let rows = self.rows?;
        let cols = self.cols;
        let (first, last) = (self.bins.front()?, self.bins.back()?);
        let mut pixels = vec![0.0f32; rows * cols];
        let mut filled = vec![false; cols];
        let mut reason = String::new();
        for bin in &self.bins {
            let c = (bin.index - first_index) as usize;
            if c >= cols {
                continue;
            }
            filled[c] = true;
            let inv = 1.0 / bin.count as f32;
            for (r, s) in bin.sum.iter().enumerate() {
                pixels[r * cols + c] = s * inv;
            }
        }
        rubber_band(&mut pixels, rows, cols, &filled);
        if first.segment != last.segment {
            reason = "the encoder reverses inside the submap".into();
        }
        let (t0, t1) = (first.first_stamp_ns, last.last_stamp_ns);
        let v = &self.params.validity;
        let (mut gz, mut ay) = (0.0f64, 0.0f64);
        for &(t, g, a) in &self.imu {
            if t >= t0 && t <= t1 {
                gz = gz.max(g);
                ay = ay.max(a);
            }
        }
        if reason.is_empty() && gz > v.max_gyro_z_radps {
            reason = format!("|gyro z| reaches {gz:.3} rad/s (max {})", v.max_gyro_z_radps);
        }
        if reason.is_empty() && ay > v.max_accel_y_mps2 {
            reason = format!("|accel y| reaches {ay:.3} m/s^2 (max {})", v.max_accel_y_mps2);
        }
        let mut longest_gap = 0usize;
        let mut run = 0usize;
        for f in &filled {
            run = if *f { 0 } else { run + 1 };
            longest_gap = longest_gap.max(run);
        }
        let gap_m = longest_gap as f64 * self.params.resolution_m;
        if reason.is_empty() && gap_m > v.max_gap_m + 1e-12 {
            reason = format!("{gap_m:.3} m without a trace (max {} m)", v.max_gap_m);
        }
        let valid = reason.is_empty();
        // Wheel distance at a column centre from the nearest bin's mean (exact while the
        // encoder moves one way: distance and travel differ by a constant there).
        let res = self.params.resolution_m;
        let distance_at = |bin: &Bin, c: usize| {
            let n = f64::from(bin.count);
            let (d, s) = (bin.distance_sum_m / n, bin.travel_sum_m / n);
            let centre = (first_index as f64 + c as f64 + 0.5) * res;
            d + f64::from(bin.direction) * (centre - s)
        };
        let bins_inside = self.bins.iter().filter(|b| b.index - first_index < cols as i64);
        // relative to t0, so that f64 keeps nanoseconds
        let column_stamps_ns = column_stamps(
            bins_inside.map(|b| {
                let mean_ns = b.stamp_sum_ns / i128::from(b.count) - i128::from(t0);
                (b.travel_sum_m / f64::from(b.count), mean_ns as f64)
            }),
            (0..cols).map(|c| (first_index as f64 + c as f64 + 0.5) * res),
        )
        .into_iter()
        .map(|dt| t0 + dt)
        .collect();
        let start_distance_m = distance_at(first, 0);
        let end_distance_m = distance_at(last, cols - 1);
        let id = self.next_id;
        self.next_id += 1;
        if valid {
            self.stats.valid += 1;
        } else {
            self.stats.invalid += 1;
            if !self.params.emit_invalid {
                return None;
            }
        }
        Some(Submap {
            id,
            start_stamp_ns: t0,
            end_stamp_ns: t1,
            start_distance_m,
            end_distance_m,
            resolution_m: res,
            rows,
            cols,
            start_pose: first.first_pose,
            end_pose: last.last_pose,
            saliency: saliency(&pixels, rows, cols),
            valid,
            invalid_reason: reason,
            filled_cols: filled.iter().filter(|f| **f).count(),
            pixels,
            column_stamps_ns,
        })
    }
}

/// The stamp at each of `centres` (travel, m, increasing) on the piecewise-linear track
/// through `points` (a bin's mean travel and mean stamp, in travel order), extended past
/// the ends along the first and last pieces; with one point, its stamp everywhere.
fn column_stamps(points: impl Iterator<Item = (f64, f64)>, centres: impl Iterator<Item = f64>) -> Vec<i64> {
    let points: Vec<(f64, f64)> = points.collect();
    let mut k = 0;
    centres
        .map(|x| {
            let stamp = match points.as_slice() {
                [] => 0.0,
                [(_, t)] => *t,
                _ => {
                    while k + 2 < points.len() && points[k + 1].0 < x {
                        k += 1;
                    }
                    let ((x0, t0), (x1, t1)) = (points[k], points[k + 1]);
                    if x1 > x0 {
                        t0 + (t1 - t0) * (x - x0) / (x1 - x0)
                    } else {
                        t0
                    }
                }
            };
            stamp.round() as i64
        })
        .collect()
}

/// The wheel sample interpolated at `stamp_ns` between `a` (if any) and `b`.
fn interpolate(a: Option<&WheelSample>, b: &WheelSample, stamp_ns: i64) -> WheelSample {
    let Some(a) = a else {
        return WheelSample { stamp_ns, ..*b };
    };
    if b.stamp_ns <= a.stamp_ns || stamp_ns <= a.stamp_ns {
        let nearest = if stamp_ns <= a.stamp_ns { a } else { b };
        return WheelSample { stamp_ns, ..*nearest };
    }
    let w = (stamp_ns - a.stamp_ns) as f64 / (b.stamp_ns - a.stamp_ns) as f64;
    let lerp = |x: f64, y: f64| x + w * (y - x);
    WheelSample {
        stamp_ns,
        distance_m: lerp(a.distance_m, b.distance_m),
        travel_m: lerp(a.travel_m, b.travel_m),
        segment: b.segment,
        direction: b.direction,
        pose: Planar {
            x_m: lerp(a.pose.x_m, b.pose.x_m),
            y_m: lerp(a.pose.y_m, b.pose.y_m),
            yaw_rad: lerp(a.pose.yaw_rad, b.pose.yaw_rad),
        },
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ValidityParams;

    const ROWS: usize = 8;
    const TRACE_HZ: f64 = 100.0;
    const WHEEL_HZ: f64 = 50.0;
    const IMU_HZ: f64 = 200.0;

    /// The ground under wheel distance `d`: row `r` holds `sin(3 d + r)` (a pattern the
    /// resampling must put at the right column).
    fn ground(d: f64, r: usize) -> f32 {
        (3.0 * d + r as f64).sin() as f32
    }

    /// Drives the distance profile `distance(t)` for `duration_s` with the yaw rate `gyro(t)`;
    /// returns every submap.
    fn drive(
        params: SubmapParams,
        duration_s: f64,
        distance: impl Fn(f64) -> f64,
        gyro: impl Fn(f64) -> f64,
    ) -> (Vec<Submap>, SubmapStats) {
        let mut b = SubmapBuilder::new(params).expect("test input is valid");
        let mut out = Vec::new();
        // merge the three streams in stamp order
        let mut events: Vec<(i64, u8)> = Vec::new();
        for (hz, kind) in [(TRACE_HZ, 0u8), (WHEEL_HZ, 1), (IMU_HZ, 2)] {
            let n = (duration_s * hz) as i64;
            events.extend((0..=n).map(|k| ((k as f64 / hz * 1e9).round() as i64, kind)));
        }
        events.sort();
        for (t, kind) in events {
            let ts = t as f64 * 1e-9;
            match kind {
                0 => {
                    let d = distance(ts);
                    let trace: Vec<f32> = (0..ROWS).map(|r| ground(d, r)).collect();
                    out.extend(b.trace(t, &trace).expect("test input is valid"));
                }
                1 => out.extend(b.wheel(t, distance(ts)).expect("test input is valid")),
                _ => b.imu(t, gyro(ts), 0.0).expect("test input is valid"),
            }
        }
        out.extend(b.finish());
        (out, b.stats())
    }

    #[test]
    fn straight_drive_gives_a_submap_every_spacing_with_the_ground_in_place() {
        let (maps, stats) = drive(SubmapParams::default(), 10.0, |t| 0.5 * t, |_| 0.0);
        // 5 m of travel: the first submap at 3 m, then one per 0.02 m
        assert_eq!(maps.len(), 101, "{stats:?}");
        assert_eq!(stats.invalid, 0);
        for m in &maps {
            assert!(m.valid);
            assert_eq!((m.rows, m.cols), (ROWS, 200));
            assert!((m.end_distance_m - m.start_distance_m - 199.0 * 0.015).abs() < 1e-9);
            // 100 traces/s at 0.5 m/s: 0.005 m apart, every column holds traces
            assert_eq!(m.filled_cols, 200);
            for c in [0, 57, 199] {
                let d = m.start_distance_m + c as f64 * 0.015;
                for r in 0..ROWS {
                    // a column averages the traces over its 0.015 m: within the pattern's change
                    let err = (m.pixels[r * m.cols + c] - ground(d, r)).abs();
                    assert!(err < 0.03, "submap {} col {c} row {r}: err {err}", m.id);
                }
            }
            assert!(
                (m.end_pose.x_m - m.start_pose.x_m - 3.0).abs() < 0.02,
                "{:?}",
                m.end_pose
            );
            assert!(m.saliency > 0.5, "{}", m.saliency);
        }
        // consecutive submaps start 0.02 m apart
        let step = maps[1].start_distance_m - maps[0].start_distance_m;
        assert!((step - 0.02).abs() < 0.015 + 1e-9, "{step}");
        let span = maps[100].start_distance_m - maps[0].start_distance_m;
        assert!((span - 2.0).abs() < 0.02, "{span}");
    }

    /// The largest error, s, of `m`'s column stamps against the moment `distance` (which
    /// turns back only at `turn_s`) passed each column's centre.
    fn column_stamp_error_s(m: &Submap, distance: &impl Fn(f64) -> f64, turn_s: f64) -> f64 {
        let (mut t0, mut t1) = (m.start_stamp_ns as f64 * 1e-9 - 0.1, m.end_stamp_ns as f64 * 1e-9 + 0.1);
        if t0 >= turn_s - 0.1 {
            t0 = t0.max(turn_s);
        } else {
            t1 = t1.min(turn_s);
        }
        let rising = distance(t1) > distance(t0);
        let step = (m.end_distance_m - m.start_distance_m) / (m.cols - 1) as f64;
        assert_eq!(m.column_stamps_ns.len(), m.cols);
        (0..m.cols)
            .filter_map(|c| {
                let d = m.start_distance_m + step * c as f64;
                // a centre the rig never reached (past a turn) has no true moment
                if (distance(t0) < d) != rising || (distance(t1) > d) != rising {
                    return None;
                }
                let (mut lo, mut hi) = (t0, t1);
                for _ in 0..60 {
                    let mid = 0.5 * (lo + hi);
                    if (distance(mid) < d) == rising {
                        lo = mid
                    } else {
                        hi = mid
                    }
                }
                Some((m.column_stamps_ns[c] as f64 * 1e-9 - lo).abs())
            })
            .fold(0.0, f64::max)
    }

    #[test]
    fn column_stamps_give_when_the_rig_was_over_each_column() {
        // speed between 0.34 and 0.66 m/s; then 2 m/s, where some columns hold no trace;
        // then back and forth
        // (duration, the moment it turns back, distance)
        type Profile = (f64, f64, Box<dyn Fn(f64) -> f64>);
        let profiles: [Profile; 3] = [
            (12.0, f64::INFINITY, Box::new(|t| 0.5 * t + 0.2 * (0.8 * t).sin())),
            (3.0, f64::INFINITY, Box::new(|t| 2.0 * t)),
            (
                20.0,
                9.0,
                Box::new(|t| if t < 9.0 { 0.5 * t } else { 4.5 - 0.5 * (t - 9.0) }),
            ),
        ];
        for (i, (duration_s, turn_s, distance)) in profiles.iter().enumerate() {
            let (maps, _) = drive(SubmapParams::default(), *duration_s, distance, |_| 0.0);
            let valid: Vec<_> = maps.iter().filter(|m| m.valid).collect();
            assert!(!valid.is_empty(), "profile {i}");
            for m in valid {
                let err = column_stamp_error_s(m, distance, *turn_s);
                // traces 10 ms apart, wheel samples 20 ms apart: a millisecond or two
                assert!(err < 0.002, "profile {i} submap {}: {err} s", m.id);
            }
        }
    }

    #[test]
    fn gaps_between_sparse_traces_are_interpolated() {
        // 2 m/s with 100 traces/s: a trace every 0.02 m, bins of 0.015 m: some stay empty
        let (maps, _) = drive(SubmapParams::default(), 3.0, |t| 2.0 * t, |_| 0.0);
        let m = &maps[0];
        assert!(m.filled_cols < 200 && m.filled_cols > 100, "{}", m.filled_cols);
        for c in 1..199 {
            let d = m.start_distance_m + c as f64 * 0.015;
            let err = (m.pixels[2 * m.cols + c] - ground(d, 2)).abs();
            assert!(err < 0.06, "col {c}: err {err}");
        }
    }

    #[test]
    fn forward_backward_motion_splits_into_valid_submaps_on_each_leg() {
        // 4 m forward in 8 s, then 4 m back
        let profile = |t: f64| if t <= 8.0 { 0.5 * t } else { 4.0 - 0.5 * (t - 8.0) };
        let params = SubmapParams {
            emit_invalid: true,
            ..SubmapParams::default()
        };
        let (maps, stats) = drive(params, 16.0, profile, |_| 0.0);
        let valid: Vec<&Submap> = maps.iter().filter(|m| m.valid).collect();
        let invalid: Vec<&Submap> = maps.iter().filter(|m| !m.valid).collect();
        assert_eq!(stats.valid as usize, valid.len());
        // about 51 valid on each leg; the submaps spanning the turn-around are invalid
        assert!((98..=104).contains(&valid.len()), "{}", valid.len());
        assert!((145..=152).contains(&invalid.len()), "{}", invalid.len());
        assert!(invalid.iter().all(|m| m.invalid_reason.contains("reverses")));
        let back = valid.last().expect("test input is valid");
        assert!(back.end_distance_m < back.start_distance_m);
        // the backward leg sees the same ground: column c of the backward submap sits at the
        // distance of its centre
        for c in [0, 100, 199] {
            let d = back.start_distance_m - c as f64 * 0.015;
            let err = (back.pixels[3 * back.cols + c] - ground(d, 3)).abs();
            assert!(err < 0.03, "col {c}: err {err}");
        }
    }

    #[test]
    fn turning_faster_than_the_threshold_invalidates() {
        let params = SubmapParams {
            validity: ValidityParams {
                max_gyro_z_radps: 0.2,
                ..ValidityParams::default()
            },
            ..SubmapParams::default()
        };
        // a 0.5 rad/s turn between 7 and 7.5 s
        let (maps, stats) = drive(
            params,
            10.0,
            |t| 0.5 * t,
            |t| if (7.0..7.5).contains(&t) { 0.5 } else { 0.0 },
        );
        assert!(stats.invalid > 0 && stats.valid > 0, "{stats:?}");
        assert!(maps.iter().all(|m| m.valid));
        // every emitted submap ends before the turn or starts after it
        for m in &maps {
            let (a, b) = (m.start_stamp_ns as f64 * 1e-9, m.end_stamp_ns as f64 * 1e-9);
            assert!(b < 7.0 + 0.02 || a > 7.5 - 0.02, "{a}..{b}");
        }
    }

    #[test]
    fn a_radar_outage_longer_than_the_gap_limit_invalidates() {
        // no traces between 6.0 and 6.4 s: 0.2 m at 0.5 m/s
        let mut b = SubmapBuilder::new(SubmapParams {
            emit_invalid: true,
            ..SubmapParams::default()
        })
        .expect("test input is valid");
        let mut maps = Vec::new();
        for k in 0..=1000i64 {
            let t = k * 10_000_000;
            let ts = t as f64 * 1e-9;
            if k % 2 == 0 {
                maps.extend(b.wheel(t, 0.5 * ts).expect("test input is valid"));
            }
            if !(6.0..6.4).contains(&ts) {
                maps.extend(b.trace(t, &[ground(0.5 * ts, 0)]).expect("test input is valid"));
            }
        }
        let spans_gap = |m: &Submap| m.start_distance_m < 3.0 && m.end_distance_m > 3.2;
        assert!(maps.iter().any(spans_gap));
        for m in &maps {
            assert_eq!(
                m.valid,
                !spans_gap(m),
                "{} {}..{}",
                m.id,
                m.start_distance_m,
                m.end_distance_m
            );
            if !m.valid {
                assert!(m.invalid_reason.contains("without a trace"), "{}", m.invalid_reason);
            }
        }
    }

    #[test]
    fn bad_measurements_are_refused_with_the_reason() {
        let mut b = SubmapBuilder::new(SubmapParams::default()).expect("test input is valid");
        b.trace(10, &[1.0, 2.0]).expect("test input is valid");
        let e = b.trace(20, &[1.0, f32::NAN]).expect_err("refused").to_string();
        assert!(e.contains("sample 1 is not finite"), "{e}");
        let e = b.trace(30, &[1.0, 2.0, 3.0]).expect_err("refused").to_string();
        assert!(e.contains("3 samples, the first trace had 2"), "{e}");
        let e = b.trace(5, &[1.0, 2.0]).expect_err("refused").to_string();
        assert!(e.contains("before the previous trace"), "{e}");
        b.wheel(100, 0.0).expect("test input is valid");
        let e = b.wheel(50, 0.1).expect_err("refused").to_string();
        assert!(e.contains("before the previous one"), "{e}");
        assert!(b.wheel(200, f64::INFINITY).is_err());
        assert!(b.imu(200, f64::NAN, 0.0).is_err());
        assert_eq!(b.stats().traces, 1);
    }

    #[test]
    fn traces_without_any_wheel_are_counted() {
        let mut b = SubmapBuilder::new(SubmapParams::default()).expect("test input is valid");
        b.trace(10, &[1.0]).expect("test input is valid");
        b.trace(20, &[1.0]).expect("test input is valid");
        assert!(b.finish().is_empty());
        assert_eq!(b.stats().traces_without_wheel, 2);
    }
}

//! Scenario files: the world, the radar, the motion and the sensors of a simulated run.
//!
//! Every field is documented here; the same documentation is in the JSON schema
//! (`gprflow sim --schema`, checked in as `tools/sim/scenario.schema.json`) and in the
//! field-by-field reference `tools/sim/scenarios/README.md`, both generated from these types. Lengths are metres,
//! depths are positive downwards, angles in scenario files are degrees (`_deg`), times
//! seconds unless a name says otherwise. World coordinates: x east, y north, z up.

use std::f64::consts::TAU;

use schemars::JsonSchema;
use serde::Deserialize;

use gprflow_params::{ParamError, non_negative, positive, within};

use crate::SimError;

/// A simulated world and the runs made in it.
#[derive(Debug, Clone, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct Scenario {
    /// Name of the scenario, written into the recording's metadata.
    pub name: String,
    /// Seed of the world. The world is the same in every run of the scenario; each run's
    /// sensor noise is drawn from this seed and the run's name.
    pub seed: u64,
    /// Sensor time of the first message, ns since the Unix epoch.
    #[serde(default = "default_start_time_ns")]
    pub start_time_ns: i64,
    /// Soil, objects and texture.
    pub world: World,
    /// The ground-penetrating radar.
    pub radar: Radar,
    /// The runs (passes) made in this world; `gprflow sim --run NAME` picks one, the first by
    /// default.
    pub runs: Vec<Run>,
    /// Inertial measurement unit.
    #[serde(default)]
    pub imu: ImuConfig,
    /// Wheel encoder.
    #[serde(default)]
    pub wheel: WheelConfig,
    /// Ground truth (total station).
    #[serde(default)]
    pub truth: TruthConfig,
    /// Optional GPS/INS (WAAS grade), as used for the LGPR highway runs.
    #[serde(default)]
    pub gps: Option<GpsConfig>,
    /// Motion of the body on its suspension (roll, pitch and height wobble).
    #[serde(default)]
    pub vibration: Vibration,
}

fn default_start_time_ns() -> i64 {
    1_600_000_000_000_000_000
}

/// One pass through the world.
#[derive(Debug, Clone, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct Run {
    /// Name of the run (`map`, `track1`, ...).
    pub name: String,
    /// Where the body goes.
    pub trajectory: Trajectory,
    /// Volumetric water content added to every soil layer for this run (0 = the layers as
    /// declared, 0.1 = ten percent more water). Wetter soil is slower (travel times stretch)
    /// and more lossy (seed 001 §4.3).
    #[serde(default)]
    pub soil_moisture: f64,
    /// Change of `soil_moisture` per minute during the run (negative: drying after rain),
    /// so passes over the same ground see it wetter or drier. Held within [0, 0.5].
    #[serde(default)]
    pub soil_moisture_per_min: f64,
    /// Stand still this long before moving (lets an estimator initialise), s.
    #[serde(default = "default_pause")]
    pub start_pause_s: f64,
    /// Stand still this long after the last motion, s.
    #[serde(default = "default_pause")]
    pub end_pause_s: f64,
    /// A rig pulled or steered by hand does not retrace its planned path: a smooth sideways
    /// deviation from it, different on every pass over the same ground. None = the path as
    /// planned.
    #[serde(default)]
    pub wander: Option<Wander>,
    /// An antenna that does not keep even contact with the ground (a rig pulled by hand over
    /// a rough floor): its ringing changes strength as the air gap under it changes, along
    /// every pass and differently on each (seed 000 §3.1). None = even contact.
    #[serde(default)]
    pub ground_contact: Option<GroundContact>,
}

/// How the impulse radar's ringing (`radar.ringing`) changes with the antenna's contact with
/// the ground: its strength is multiplied by `exp(sigma x(t))`, `x` a unit Gauss-Markov
/// process in time. Background removal takes out the mean ringing, not these changes: they
/// are horizontal bands whose strength varies along the track, differently on every pass.
#[derive(Debug, Clone, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct GroundContact {
    /// RMS of the log of the ringing's strength (0.3: about +-30 %).
    pub ringing_sigma: f64,
    /// Correlation time of the changes, s.
    pub correlation_s: f64,
}

fn default_pause() -> f64 {
    2.0
}

/// Sideways deviation from the planned path, a smooth random function of the distance
/// driven (so two passes over the same ground deviate differently). It fades to zero over
/// `ramp_m` at every start and stop, where the plan turns or reverses.
#[derive(Debug, Clone, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct Wander {
    /// RMS of the sideways deviation, m.
    pub sigma_m: f64,
    /// Typical wavelength of the deviation along the path, m.
    pub wavelength_m: f64,
    /// Length over which the deviation fades in after a start and out before a stop, m.
    #[serde(default = "default_wander_ramp")]
    pub ramp_m: f64,
}

fn default_wander_ramp() -> f64 {
    1.0
}

/// The subsurface.
#[derive(Debug, Clone, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct World {
    /// Soil layers from the surface down; the first starts at depth 0.
    pub layers: Vec<Layer>,
    /// Small-scale heterogeneity: a dense field of weak scatterers.
    #[serde(default)]
    pub texture: Option<Texture>,
    /// Point objects (rocks, voids).
    #[serde(default)]
    pub points: Vec<PointObject>,
    /// Randomly placed point objects.
    #[serde(default)]
    pub random_points: Option<RandomPoints>,
    /// Linear objects (pipes, fractures) as 3-D segments.
    #[serde(default)]
    pub lines: Vec<LineObject>,
    /// A rebar grid (reinforced concrete slab).
    #[serde(default)]
    pub rebar: Option<RebarGrid>,
    /// Objects on the surface (kerbs, boxes, parked cars). They are part of the world's truth
    /// but the radar, shielded upwards, does not see them.
    #[serde(default)]
    pub clutter: Vec<SurfaceObject>,
}

/// A soil layer.
#[derive(Debug, Clone, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct Layer {
    /// Depth of the layer's top below the surface (0 for the first layer), m.
    pub top_depth_m: f64,
    /// Relative permittivity of the dry layer.
    pub eps_r: f64,
    /// Attenuation of the dry layer, dB per metre one way.
    pub attenuation_db_per_m: f64,
    /// Gentle variation of the layer's top interface (ignored for the first layer).
    #[serde(default)]
    pub undulation: Option<Undulation>,
}

/// A smooth random surface: sum of a few plane waves of about this wavelength.
#[derive(Debug, Clone, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct Undulation {
    /// Standard deviation of the interface height, m.
    pub amplitude_m: f64,
    /// Typical horizontal wavelength, m.
    pub wavelength_m: f64,
}

/// Dense weak scatterers whose strength is spatially correlated: the texture that makes one
/// place's radargram differ from another's.
#[derive(Debug, Clone, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct Texture {
    /// Scatterers per cubic metre.
    pub density_per_m3: f64,
    /// Deepest scatterer, m.
    pub max_depth_m: f64,
    /// Typical reflection strength (dimensionless, a perfect reflector is 1).
    pub strength: f64,
    /// Correlation length of the strength field, m.
    pub correlation_length_m: f64,
    /// How much of a scatterer's strength follows the correlated field (0..1); the rest is
    /// independent per scatterer.
    #[serde(default = "default_correlation")]
    pub correlation: f64,
    /// Anisotropy of the scatterers (0..1): 0 isotropic, 1 fully polarised, so that the
    /// radargram depends on the antenna's heading (seed 001 §4.5).
    #[serde(default)]
    pub polarisation: f64,
}

fn default_correlation() -> f64 {
    0.7
}

/// What a point object is made of.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize, JsonSchema, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum PointKind {
    /// A rock (a little denser than the soil).
    Rock,
    /// An air-filled void (strong, inverted-polarity reflection).
    Void,
}

/// A compact buried object.
#[derive(Debug, Clone, Deserialize, JsonSchema, serde::Serialize)]
#[serde(deny_unknown_fields)]
pub struct PointObject {
    /// Horizontal position [x, y], m.
    pub at: [f64; 2],
    /// Depth of the centre, m.
    pub depth_m: f64,
    /// Radius, m.
    pub radius_m: f64,
    /// Material.
    pub kind: PointKind,
}

/// Point objects scattered at random over an area.
#[derive(Debug, Clone, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct RandomPoints {
    /// Objects per square metre.
    pub per_m2: f64,
    /// Area corners [[x_min, y_min], [x_max, y_max]], m.
    pub area: [[f64; 2]; 2],
    /// Depth range [min, max], m.
    pub depth_m: [f64; 2],
    /// Radius range [min, max], m.
    pub radius_m: [f64; 2],
    /// Fraction of voids (the rest are rocks).
    #[serde(default)]
    pub void_fraction: f64,
}

/// What a linear object is.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize, JsonSchema, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum LineKind {
    /// Metal pipe or bar (perfect reflector).
    MetalPipe,
    /// Plastic pipe, air filled.
    PlasticPipe,
    /// Water-filled plastic pipe.
    WaterPipe,
    /// A fracture or thin wet seam (weak).
    Fracture,
}

/// A buried linear object: a 3-D segment with a radius.
#[derive(Debug, Clone, Deserialize, JsonSchema, serde::Serialize)]
#[serde(deny_unknown_fields)]
pub struct LineObject {
    /// One end [x, y, depth], m.
    pub from: [f64; 3],
    /// The other end [x, y, depth], m.
    pub to: [f64; 3],
    /// Radius, m.
    pub radius_m: f64,
    /// Material.
    pub kind: LineKind,
}

/// Reinforcing bars in two directions at one depth.
#[derive(Debug, Clone, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct RebarGrid {
    /// Corner of the grid [x, y], m.
    pub origin: [f64; 2],
    /// Size along the grid's own axes [along, across], m.
    pub size_m: [f64; 2],
    /// Bar spacing [along, across], m.
    pub spacing_m: [f64; 2],
    /// Rotation of the grid's first axis from world x, degrees.
    #[serde(default)]
    pub angle_deg: f64,
    /// Depth of the bars, m.
    pub depth_m: f64,
    /// Bar radius, m.
    #[serde(default = "default_rebar_radius")]
    pub radius_m: f64,
}

fn default_rebar_radius() -> f64 {
    0.008
}

/// An object on the surface.
#[derive(Debug, Clone, Deserialize, JsonSchema, serde::Serialize)]
#[serde(deny_unknown_fields)]
pub struct SurfaceObject {
    /// Position [x, y], m.
    pub at: [f64; 2],
    /// Footprint [length, width], m.
    pub size_m: [f64; 2],
    /// Height, m.
    pub height_m: f64,
}

/// The radar.
#[derive(Debug, Clone, Deserialize, JsonSchema)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum Radar {
    /// Single-channel impulse GPR (the thesis rig's Noggin 500).
    Impulse(ImpulseRadar),
    /// The 12-element / 11-channel SFCW array of the LGPR (seed 001 Table I).
    Lgpr(LgprRadar),
}

/// A single-channel impulse GPR. Defaults: Sensors & Software Noggin 500 as on the thesis rig.
#[derive(Debug, Clone, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct ImpulseRadar {
    /// Centre frequency of the Ricker-like pulse, Hz.
    pub center_frequency_hz: f64,
    /// Samples per trace.
    pub samples: u32,
    /// Sample interval, ns.
    pub sample_interval_ns: f64,
    /// Traces per second (a rate in time: traces bunch when the body stops).
    pub trace_rate_hz: f64,
    /// Sample index of the transmit instant (the recorder listens before it sends).
    pub time_zero_sample: f64,
    /// Antenna height above the ground, m (0: in contact, as with the thesis rig's suspension).
    pub antenna_height_m: f64,
    /// Antenna position in the body frame [x forward, y left], m.
    pub mount_m: [f64; 2],
    /// Half-width of the two-way beam, degrees (response exp(-(angle/beam)^2)).
    pub beam_half_angle_deg: f64,
    /// Counts that a perfect flat reflector 1 m below the antenna would give, before losses.
    pub reflection_counts: f64,
    /// Peak of the direct coupling (transmitter to receiver), counts; its main lobe is
    /// negative, so zero time is the first negative peak (seed 000 §3.2.2).
    pub direct_coupling_counts: f64,
    /// Repetitive ringing after the direct coupling (horizontal banding).
    pub ringing: Ringing,
    /// Low-frequency "wow" hump, counts.
    pub wow_counts: f64,
    /// Time of the wow's peak, ns.
    pub wow_time_ns: f64,
    /// DC offset, counts.
    pub dc_offset_counts: f64,
    /// Per-trace random walk of the DC offset, counts.
    pub dc_walk_counts: f64,
    /// Standard deviation of the per-trace time-zero jitter, ns.
    pub time_zero_jitter_ns: f64,
    /// White noise, counts (before quantisation to int16).
    pub noise_counts: f64,
}

impl Default for ImpulseRadar {
    fn default() -> Self {
        Self {
            center_frequency_hz: 500e6,
            samples: 201,
            sample_interval_ns: 0.2,
            trace_rate_hz: 50.0,
            time_zero_sample: 20.0,
            antenna_height_m: 0.0,
            mount_m: [0.0, 0.0],
            beam_half_angle_deg: 30.0,
            reflection_counts: 6000.0,
            direct_coupling_counts: 16000.0,
            ringing: Ringing::default(),
            wow_counts: 2500.0,
            wow_time_ns: 12.0,
            dc_offset_counts: 150.0,
            dc_walk_counts: 2.0,
            time_zero_jitter_ns: 0.05,
            noise_counts: 12.0,
        }
    }
}

/// Repetitive ringing: copies of the direct coupling every `period_ns`, each `decay` times the
/// one before; the same at every position (it is the radar, not the ground), drifting slowly.
#[derive(Debug, Clone, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct Ringing {
    /// Amplitude of the first copy relative to the direct coupling.
    pub first: f64,
    /// Ratio between successive copies.
    pub decay: f64,
    /// Spacing of the copies, ns.
    pub period_ns: f64,
    /// Relative drift of the ringing amplitude over a run (random walk, per second).
    pub drift_per_s: f64,
}

impl Default for Ringing {
    fn default() -> Self {
        Self {
            first: 0.12,
            decay: 0.6,
            period_ns: 5.2,
            drift_per_s: 0.002,
        }
    }
}

/// The LGPR's SFCW array. Defaults: seed 001 Table I.
#[derive(Debug, Clone, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct LgprRadar {
    /// First tone, Hz.
    pub start_frequency_hz: f64,
    /// Tone spacing, Hz.
    pub frequency_step_hz: f64,
    /// Number of tones.
    pub tones: u32,
    /// Antenna elements (channels = elements - 1).
    pub elements: u32,
    /// Element spacing across track, m.
    pub element_spacing_m: f64,
    /// Array height above the ground, m.
    pub height_m: f64,
    /// Sweeps per second (all channels).
    pub sweep_rate_hz: f64,
    /// Array centre in the body frame [x forward, y left], m.
    pub mount_m: [f64; 2],
    /// Half-width of the two-way beam, degrees.
    pub beam_half_angle_deg: f64,
    /// Deepest scatterer considered, m.
    pub max_depth_m: f64,
    /// Complex noise per tone relative to the direct coupling.
    pub noise: f64,
    /// Scene response of a perfect flat reflector 1 m away, relative to the direct coupling.
    pub reflection_level: f64,
    /// Element-to-element gain mismatch (standard deviation, relative).
    pub element_mismatch: f64,
    /// Thermal drift of the receive chain over a run: phase, degrees per minute.
    pub thermal_phase_drift_deg_per_min: f64,
}

impl Default for LgprRadar {
    fn default() -> Self {
        Self {
            start_frequency_hz: 100e6,
            frequency_step_hz: 6e6,
            tones: 51,
            elements: 12,
            element_spacing_m: 0.127,
            height_m: 0.1524,
            sweep_rate_hz: 126.0,
            mount_m: [0.0, 0.0],
            beam_half_angle_deg: 30.0,
            max_depth_m: 3.0,
            noise: 1e-4,
            reflection_level: 0.3,
            element_mismatch: 0.1,
            thermal_phase_drift_deg_per_min: 2.0,
        }
    }
}

/// Where the body goes. Every kind stops (and so bunches traces) at its ends and pauses.
#[derive(Debug, Clone, Deserialize, JsonSchema)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum Trajectory {
    /// Through explicit waypoints, rounding corners, stopping at the last.
    Waypoints {
        /// [x, y] points, m.
        points: Vec<[f64; 2]>,
        /// Cruise speed, m/s.
        speed_mps: f64,
        /// Corner radius, m.
        #[serde(default = "default_corner_radius")]
        corner_radius_m: f64,
        /// Stop this long at every intermediate waypoint (0: drive through), s.
        #[serde(default)]
        pause_s: f64,
    },
    /// Forward along a line, then backwards to the start (the heading stays), repeatedly.
    ForwardBackward {
        /// Start [x, y], m.
        start: [f64; 2],
        /// Heading, degrees from x.
        heading_deg: f64,
        /// Length of the line, m.
        length_m: f64,
        /// Forward-backward repetitions.
        repeats: u32,
        /// Cruise speed, m/s.
        speed_mps: f64,
        /// Stop at each end, s.
        #[serde(default = "default_turn_pause")]
        pause_s: f64,
    },
    /// A rounded rectangle driven counter-clockwise, several laps.
    Loop {
        /// Centre [x, y], m.
        center: [f64; 2],
        /// Size [along x, along y], m.
        size_m: [f64; 2],
        /// Laps.
        laps: u32,
        /// Cruise speed, m/s.
        speed_mps: f64,
        /// Corner radius, m.
        #[serde(default = "default_corner_radius")]
        corner_radius_m: f64,
    },
    /// Parallel rows joined by U-turns (boustrophedon).
    Lawnmower {
        /// Start of the first row [x, y], m.
        origin: [f64; 2],
        /// Row direction, degrees from x.
        heading_deg: f64,
        /// Row length, m.
        length_m: f64,
        /// Number of rows.
        rows: u32,
        /// Row spacing (to the left of the first row), m.
        spacing_m: f64,
        /// Cruise speed, m/s.
        speed_mps: f64,
    },
    /// A long meandering drive that never comes back.
    LongDrive {
        /// Start [x, y], m.
        start: [f64; 2],
        /// Mean heading, degrees from x.
        heading_deg: f64,
        /// Length along the mean heading, m.
        length_m: f64,
        /// Lateral meander amplitude, m.
        #[serde(default)]
        meander_m: f64,
        /// Meander wavelength, m.
        #[serde(default = "default_meander_wavelength")]
        meander_wavelength_m: f64,
        /// Cruise speed, m/s.
        speed_mps: f64,
    },
    /// A closed highway lap (two straights joined by half circles), for LGPR mapping and
    /// tracking passes.
    Highway {
        /// Lap length, m (seed 001: 1.6 km).
        #[serde(default = "default_lap_length")]
        lap_length_m: f64,
        /// Radius of the bends, m.
        #[serde(default = "default_bend_radius")]
        bend_radius_m: f64,
        /// Speed, km/h (seed 001: 16 to 97).
        speed_kmh: f64,
        /// Lateral offset from the mapping line, positive to the left, m.
        #[serde(default)]
        lateral_offset_m: f64,
        /// Laps.
        #[serde(default = "default_laps")]
        laps: u32,
    },
}

fn default_corner_radius() -> f64 {
    0.5
}
fn default_turn_pause() -> f64 {
    1.0
}
fn default_meander_wavelength() -> f64 {
    20.0
}
fn default_lap_length() -> f64 {
    1600.0
}
fn default_bend_radius() -> f64 {
    60.0
}
fn default_laps() -> u32 {
    1
}

/// Roll, pitch and height wobble of the body: each a sum of three sinusoids of random
/// phase and frequency, scaled to these peak values (seed 001 Table VI for a car).
#[derive(Debug, Clone, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct Vibration {
    /// Peak roll, degrees.
    pub roll_deg: f64,
    /// Peak pitch, degrees.
    pub pitch_deg: f64,
    /// Peak height change, m.
    pub height_m: f64,
    /// Typical frequency, Hz.
    pub frequency_hz: f64,
}

impl Default for Vibration {
    fn default() -> Self {
        Self {
            roll_deg: 0.3,
            pitch_deg: 0.3,
            height_m: 0.002,
            frequency_hz: 1.5,
        }
    }
}

/// IMU noise and rate. Defaults: the thesis rig's XSENS MTi-30
/// (`shared/data/imu/xsens_mti30_allan.yaml`, average axes).
#[derive(Debug, Clone, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct ImuConfig {
    /// Samples per second.
    pub rate_hz: f64,
    /// Gyro white noise density, rad/s/sqrt(Hz).
    pub gyro_noise_density: f64,
    /// Gyro bias random walk, rad/s^2/sqrt(Hz).
    pub gyro_random_walk: f64,
    /// Accelerometer white noise density, m/s^2/sqrt(Hz).
    pub accel_noise_density: f64,
    /// Accelerometer bias random walk, m/s^3/sqrt(Hz).
    pub accel_random_walk: f64,
    /// Standard deviation of the initial gyro bias, rad/s.
    pub gyro_bias_sigma: f64,
    /// Standard deviation of the initial accelerometer bias, m/s^2.
    pub accel_bias_sigma: f64,
    /// Standard deviation of the orientation the IMU reports (its own filter), degrees.
    pub orientation_sigma_deg: f64,
}

impl Default for ImuConfig {
    fn default() -> Self {
        Self {
            rate_hz: 200.0,
            gyro_noise_density: 2.278_106_849_083_245e-3,
            gyro_random_walk: 5.017_833_822_063_076e-5,
            accel_noise_density: 8.273_941_434_987_052e-3,
            accel_random_walk: 1.331_101_547_611_752e-4,
            gyro_bias_sigma: 2e-3,
            accel_bias_sigma: 2e-2,
            orientation_sigma_deg: 0.5,
        }
    }
}

/// Wheel encoder. Defaults: the thesis rig's 1024 PPR quadrature encoder.
#[derive(Debug, Clone, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct WheelConfig {
    /// Readings per second.
    pub rate_hz: f64,
    /// Pulses per revolution.
    pub pulses_per_revolution: u32,
    /// Nominal wheel radius, m.
    pub wheel_radius_m: f64,
    /// True radius / nominal radius - 1 (scale error).
    pub scale_error: f64,
    /// Slip: fraction of the distance lost per m/s^2 of along-track acceleration.
    pub slip_per_accel: f64,
    /// Random slip, standard deviation of the per-reading fraction of distance lost.
    pub slip_noise: f64,
}

impl Default for WheelConfig {
    fn default() -> Self {
        Self {
            rate_hz: 50.0,
            pulses_per_revolution: 1024,
            wheel_radius_m: 0.05,
            scale_error: 0.01,
            slip_per_accel: 0.01,
            slip_noise: 0.01,
        }
    }
}

/// Ground truth (a robotic total station tracking a prism on the body).
#[derive(Debug, Clone, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct TruthConfig {
    /// Poses per second.
    pub rate_hz: f64,
    /// Position noise, m (a total station: a few mm).
    pub noise_m: f64,
}

impl Default for TruthConfig {
    fn default() -> Self {
        Self {
            rate_hz: 20.0,
            noise_m: 0.003,
        }
    }
}

/// GPS/INS with WAAS-grade error: a smooth (second-order Gauss-Markov) position error, as the
/// INS between fixes makes it.
#[derive(Debug, Clone, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct GpsConfig {
    /// Fixes per second.
    pub rate_hz: f64,
    /// Horizontal RMS error, m (WAAS: about 0.35).
    pub horizontal_rms_m: f64,
    /// Vertical RMS error, m.
    pub vertical_rms_m: f64,
    /// Correlation time of the error, s.
    pub correlation_time_s: f64,
}

impl Default for GpsConfig {
    fn default() -> Self {
        Self {
            rate_hz: 10.0,
            horizontal_rms_m: 0.35,
            vertical_rms_m: 0.5,
            correlation_time_s: 60.0,
        }
    }
}

impl Scenario {
    /// The run called `name`, or the first.
    ///
    /// # Errors
    /// [`SimError::UnknownRun`].
    pub fn run(&self, name: Option<&str>) -> Result<&Run, SimError> {
        match name {
            None => self.runs.first(),
            Some(n) => self.runs.iter().find(|r| r.name == n),
        }
        .ok_or_else(|| SimError::UnknownRun {
            name: name.unwrap_or("").to_owned(),
            known: self.runs.iter().map(|r| r.name.clone()).collect(),
        })
    }

    /// The JSON schema of scenario files, generated from these types.
    pub fn json_schema() -> schemars::Schema {
        schemars::schema_for!(Scenario)
    }

    /// Checks the numbers of every field (the path's feasibility is checked by [`Scenario::parse`]).
    pub(crate) fn validate(&self) -> gprflow_params::Result {
        if self.runs.is_empty() {
            return Err(ParamError::new("runs", "at least one run is needed"));
        }
        if self.world.layers.is_empty() {
            return Err(ParamError::new("world.layers", "at least one layer is needed"));
        }
        let mut last_top = -1.0;
        for (i, layer) in self.world.layers.iter().enumerate() {
            let key = |f: &str| format!("world.layers.{i}.{f}");
            if i == 0 && layer.top_depth_m != 0.0 {
                return Err(ParamError::new(
                    &key("top_depth_m"),
                    "the first layer starts at depth 0",
                ));
            }
            if layer.top_depth_m.is_nan() || layer.top_depth_m <= last_top {
                return Err(ParamError::new(&key("top_depth_m"), "layers must get deeper"));
            }
            last_top = layer.top_depth_m;
            if !(layer.eps_r.is_finite() && layer.eps_r >= 1.0) {
                return Err(ParamError::new(
                    &key("eps_r"),
                    format!("must be >= 1, got {}", layer.eps_r),
                ));
            }
            non_negative(&key("attenuation_db_per_m"), layer.attenuation_db_per_m)?;
            if let Some(u) = &layer.undulation {
                non_negative(&key("undulation.amplitude_m"), u.amplitude_m)?;
                positive(&key("undulation.wavelength_m"), u.wavelength_m)?;
            }
        }
        if let Some(t) = &self.world.texture {
            non_negative("world.texture.density_per_m3", t.density_per_m3)?;
            if t.density_per_m3 > 5000.0 {
                return Err(ParamError::new("world.texture.density_per_m3", "at most 5000"));
            }
            positive("world.texture.max_depth_m", t.max_depth_m)?;
            non_negative("world.texture.strength", t.strength)?;
            positive("world.texture.correlation_length_m", t.correlation_length_m)?;
            within("world.texture.correlation", t.correlation, 0.0, 1.0)?;
            within("world.texture.polarisation", t.polarisation, 0.0, 1.0)?;
        }
        for (i, p) in self.world.points.iter().enumerate() {
            positive(&format!("world.points.{i}.depth_m"), p.depth_m)?;
            positive(&format!("world.points.{i}.radius_m"), p.radius_m)?;
        }
        for (i, l) in self.world.lines.iter().enumerate() {
            positive(&format!("world.lines.{i}.radius_m"), l.radius_m)?;
            positive(&format!("world.lines.{i}.from.2"), l.from[2])?;
            positive(&format!("world.lines.{i}.to.2"), l.to[2])?;
        }
        if let Some(r) = &self.world.random_points {
            non_negative("world.random_points.per_m2", r.per_m2)?;
            within("world.random_points.void_fraction", r.void_fraction, 0.0, 1.0)?;
        }
        if let Some(r) = &self.world.rebar {
            positive("world.rebar.spacing_m.0", r.spacing_m[0])?;
            positive("world.rebar.spacing_m.1", r.spacing_m[1])?;
            positive("world.rebar.depth_m", r.depth_m)?;
        }
        match &self.radar {
            Radar::Impulse(r) => {
                positive("radar.center_frequency_hz", r.center_frequency_hz)?;
                positive("radar.sample_interval_ns", r.sample_interval_ns)?;
                positive("radar.trace_rate_hz", r.trace_rate_hz)?;
                positive("radar.beam_half_angle_deg", r.beam_half_angle_deg)?;
                non_negative("radar.antenna_height_m", r.antenna_height_m)?;
                non_negative("radar.noise_counts", r.noise_counts)?;
                if r.samples == 0 || r.samples > 65_536 {
                    return Err(ParamError::new(
                        "radar.samples",
                        format!("must be 1..=65536, got {}", r.samples),
                    ));
                }
            }
            Radar::Lgpr(r) => {
                positive("radar.frequency_step_hz", r.frequency_step_hz)?;
                positive("radar.sweep_rate_hz", r.sweep_rate_hz)?;
                positive("radar.element_spacing_m", r.element_spacing_m)?;
                positive("radar.beam_half_angle_deg", r.beam_half_angle_deg)?;
                positive("radar.max_depth_m", r.max_depth_m)?;
                if r.elements < 2 || r.tones == 0 {
                    return Err(ParamError::new("radar.elements", "need at least 2 elements and 1 tone"));
                }
            }
        }
        positive("imu.rate_hz", self.imu.rate_hz)?;
        positive("wheel.rate_hz", self.wheel.rate_hz)?;
        positive("wheel.wheel_radius_m", self.wheel.wheel_radius_m)?;
        positive("truth.rate_hz", self.truth.rate_hz)?;
        if let Some(g) = &self.gps {
            positive("gps.rate_hz", g.rate_hz)?;
            positive("gps.correlation_time_s", g.correlation_time_s)?;
        }
        for (i, run) in self.runs.iter().enumerate() {
            non_negative(&format!("runs.{i}.soil_moisture"), run.soil_moisture)?;
            if run.soil_moisture > 0.5 {
                return Err(ParamError::new(&format!("runs.{i}.soil_moisture"), "at most 0.5"));
            }
            if !run.soil_moisture_per_min.is_finite() || run.soil_moisture_per_min.abs() > 0.1 {
                return Err(ParamError::new(
                    &format!("runs.{i}.soil_moisture_per_min"),
                    format!("must be finite and within +-0.1, got {}", run.soil_moisture_per_min),
                ));
            }
            non_negative(&format!("runs.{i}.start_pause_s"), run.start_pause_s)?;
            non_negative(&format!("runs.{i}.end_pause_s"), run.end_pause_s)?;
            run.trajectory
                .validate()
                .map_err(|e| e.within(&format!("runs.{i}.trajectory")))?;
            if let Some(c) = &run.ground_contact {
                let key = |f: &str| format!("runs.{i}.ground_contact.{f}");
                non_negative(&key("ringing_sigma"), c.ringing_sigma)?;
                if c.ringing_sigma > 3.0 {
                    return Err(ParamError::new(
                        &key("ringing_sigma"),
                        format!("at most 3, got {}", c.ringing_sigma),
                    ));
                }
                positive(&key("correlation_s"), c.correlation_s)?;
            }
            if let Some(w) = &run.wander {
                let key = |f: &str| format!("runs.{i}.wander.{f}");
                non_negative(&key("sigma_m"), w.sigma_m)?;
                positive(&key("wavelength_m"), w.wavelength_m)?;
                positive(&key("ramp_m"), w.ramp_m)?;
            }
        }
        Ok(())
    }
}

impl Trajectory {
    /// Checks the trajectory's numbers; the error names the field.
    fn validate(&self) -> gprflow_params::Result {
        match self {
            Trajectory::Waypoints {
                points,
                speed_mps,
                corner_radius_m,
                ..
            } => {
                positive("speed_mps", *speed_mps)?;
                positive("corner_radius_m", *corner_radius_m)?;
                if points.len() < 2 {
                    return Err(ParamError::new("points", "at least two waypoints"));
                }
                if points.windows(2).any(|w| w[0] == w[1]) {
                    return Err(ParamError::new("points", "two consecutive waypoints are equal"));
                }
                Ok(())
            }
            Trajectory::ForwardBackward {
                length_m,
                speed_mps,
                repeats,
                ..
            } => {
                positive("length_m", *length_m)?;
                positive("speed_mps", *speed_mps)?;
                if *repeats == 0 {
                    return Err(ParamError::new("repeats", "at least 1"));
                }
                Ok(())
            }
            Trajectory::Loop {
                size_m,
                laps,
                speed_mps,
                corner_radius_m,
                ..
            } => {
                positive("size_m.0", size_m[0])?;
                positive("size_m.1", size_m[1])?;
                positive("speed_mps", *speed_mps)?;
                positive("corner_radius_m", *corner_radius_m)?;
                if *laps == 0 {
                    return Err(ParamError::new("laps", "at least 1"));
                }
                Ok(())
            }
            Trajectory::Lawnmower {
                length_m,
                rows,
                spacing_m,
                speed_mps,
                ..
            } => {
                positive("length_m", *length_m)?;
                positive("spacing_m", *spacing_m)?;
                positive("speed_mps", *speed_mps)?;
                if *rows == 0 {
                    return Err(ParamError::new("rows", "at least 1"));
                }
                Ok(())
            }
            Trajectory::LongDrive {
                length_m,
                meander_m,
                meander_wavelength_m,
                speed_mps,
                ..
            } => {
                positive("length_m", *length_m)?;
                positive("speed_mps", *speed_mps)?;
                positive("meander_wavelength_m", *meander_wavelength_m)?;
                if !(meander_m.is_finite() && *meander_m >= 0.0 && *meander_m < meander_wavelength_m / 4.0) {
                    return Err(ParamError::new(
                        "meander_m",
                        format!("must be in [0, meander_wavelength_m / 4), got {meander_m}"),
                    ));
                }
                Ok(())
            }
            Trajectory::Highway {
                lap_length_m,
                bend_radius_m,
                speed_kmh,
                lateral_offset_m,
                laps,
            } => {
                positive("speed_kmh", *speed_kmh)?;
                positive("bend_radius_m", *bend_radius_m)?;
                if lap_length_m.is_nan() || *lap_length_m <= TAU * bend_radius_m {
                    return Err(ParamError::new(
                        "lap_length_m",
                        "must exceed the two bends (2 pi bend_radius_m)",
                    ));
                }
                if lateral_offset_m.is_nan() || lateral_offset_m.abs() >= *bend_radius_m {
                    return Err(ParamError::new(
                        "lateral_offset_m",
                        "must be smaller than the bend radius",
                    ));
                }
                if *laps == 0 {
                    return Err(ParamError::new("laps", "at least 1"));
                }
                Ok(())
            }
        }
    }
}

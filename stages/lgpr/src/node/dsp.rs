//! The `lgpr_dsp` stage: frequency-domain sweeps in, time-domain sweeps out, through
//! [`SfcwChain`]. The along-track distance between sweeps, which the IIR high-pass needs
//! (eq. 7), comes from the wheel odometry, extrapolated to the sweep stamp with the last speed.

use std::borrow::Cow;

use gprflow_msg::{Header, Message, Sweep, WheelOdometry};
use gprflow_stage::{
    Drops, Input, InputPorts, InputSpec, Output, Outputs, ParamError, PortSpec, Ports, Stage, StageError,
};

use crate::Error;
use crate::sfcw::{FactoryCalibration, SfcwChain, SfcwParams};

/// The LGPR sweep chain stage. Output sweeps are `domain` 1 (time): per channel
/// `keep_samples` real samples `sample_interval_ns` apart; sample 0 is at `-delay_ns`
/// (the 8 ns delay keeps the negative part of the pulse at the start).
#[derive(Debug)]
pub struct LgprDspStage {
    params: SfcwParams,
    chain: Option<SfcwChain>,
    factory: Option<FactoryCalibration>,
    /// A factory calibration input is connected: sweeps wait for it.
    wants_factory: bool,
    out: Output<Sweep<'static>>,
    /// (stamp, distance, speed) of the last wheel message.
    wheel: Option<(i64, f64, f64)>,
    last_distance_m: Option<f64>,
    buffer: Vec<f32>,
    drops: Drops,
    before_factory: u64,
}

impl LgprDspStage {
    /// The distance at `stamp_ns`: the last wheel distance advanced at its speed.
    fn distance_at(&self, stamp_ns: i64) -> Option<f64> {
        let (t, d, v) = self.wheel?;
        let dt = ((stamp_ns - t) as f64 * 1e-9).max(0.0);
        Some(d + if v.is_finite() { v * dt } else { 0.0 })
    }

    fn sweep(&mut self, input: &Input<'_>, s: &Sweep<'_>, out: &mut Outputs) -> Result<(), StageError> {
        if s.domain != Sweep::DOMAIN_FREQUENCY {
            self.drops.record(
                Self::NAME,
                input,
                &format_args!("domain {}: not a frequency-domain sweep", s.domain),
            );
            return Ok(());
        }
        if self.chain.is_none() && self.wants_factory && self.factory.is_none() {
            self.before_factory += 1;
            return Ok(());
        }
        if self.chain.is_none() {
            let chain = SfcwChain::new(
                self.params.clone(),
                s.channel_count as usize,
                s.bin_count as usize,
                s.start_frequency_hz,
                s.frequency_step_hz,
                self.factory.take(),
            )
            // parameters were checked at start-up: what fails here is the sweep's shape
            .map_err(|e| {
                StageError::failed(format!(
                    "the first sweep (seq {}) does not suit the chain: {e}",
                    input.seq()
                ))
            })?;
            tracing::info!(
                channels = chain.channels(),
                tones = chain.bins(),
                samples = chain.out_samples(),
                sample_interval_ns = chain.sample_interval_ns(),
                "lgpr_dsp: chain built from the first sweep"
            );
            self.buffer = vec![0.0; chain.channels() * chain.out_samples()];
            self.chain = Some(chain);
        }
        let distance = self.distance_at(input.stamp_ns());
        let step = match (distance, self.last_distance_m) {
            (Some(d), Some(prev)) => (d - prev).abs(),
            _ => 0.0,
        };
        let Some(chain) = self.chain.as_mut() else {
            return Ok(());
        };
        match chain.process(&s.values, &s.calibration, step, &mut self.buffer) {
            Ok(()) => {}
            Err(
                e @ (Error::Size { .. } | Error::NonFinite { .. } | Error::ZeroDivisor { .. } | Error::Distance { .. }),
            ) => {
                self.drops.record(Self::NAME, input, &e);
                return Ok(());
            }
            Err(e) => return Err(StageError::failed(e)),
        }
        if distance.is_some() {
            self.last_distance_m = distance;
        }
        let msg = Sweep {
            header: Header::new(input.stamp_ns(), &s.header.frame_id),
            domain: Sweep::DOMAIN_TIME,
            channel_count: chain.channels() as u32,
            bin_count: chain.out_samples() as u32,
            start_frequency_hz: s.start_frequency_hz,
            frequency_step_hz: s.frequency_step_hz,
            sample_interval_ns: chain.sample_interval_ns(),
            values: Cow::Owned(self.buffer.clone()),
            calibration: Cow::Borrowed(&[]),
        };
        out.send(self.out, &msg)
    }
}

impl Stage for LgprDspStage {
    type Params = SfcwParams;
    const NAME: &'static str = "lgpr_dsp";
    const ABOUT: &'static str = "LGPR sweep chain: self and factory calibration, delay, Chebyshev window, IFFT, distance IIR high-pass, range gain";

    fn inputs() -> InputPorts {
        let port = |name: &str, ty: &str, optional: bool| InputSpec {
            port: PortSpec::new(name, ty),
            optional,
        };
        InputPorts::Fixed(vec![
            // declared first: at equal stamps the calibration is delivered before a sweep
            port("factory_calibration", Sweep::TYPE_NAME, true),
            port("wheel", WheelOdometry::TYPE_NAME, false),
            port("sweep", Sweep::TYPE_NAME, false),
        ])
    }

    fn outputs(_: &Self::Params) -> Result<Vec<PortSpec>, ParamError> {
        Ok(vec![PortSpec::new("sweep", Sweep::TYPE_NAME)])
    }

    fn check_params(params: &Self::Params) -> Result<(), ParamError> {
        // every parameter checked before the start, not at the first sweep (a typical 11 x 51
        // array)
        match SfcwChain::new(params.clone(), 11, 51, 100e6, 6e6, None) {
            Ok(_) => Ok(()),
            Err(Error::Param(e)) => Err(e),
            Err(other) => Err(ParamError::new("", other.to_string())),
        }
    }

    fn create(params: Self::Params, ports: &Ports) -> Result<Self, StageError> {
        Ok(Self {
            params,
            chain: None,
            factory: None,
            wants_factory: ports.input("factory_calibration").is_some(),
            out: ports.output("sweep")?,
            wheel: None,
            last_distance_m: None,
            buffer: Vec::new(),
            drops: Drops::new(),
            before_factory: 0,
        })
    }

    fn on_message(&mut self, input: Input<'_>, out: &mut Outputs) -> Result<(), StageError> {
        match input.name() {
            "factory_calibration" if self.factory.is_none() && self.chain.is_none() => {
                let s: Sweep = input.decode()?;
                let f = FactoryCalibration::new(
                    &s.values,
                    &s.calibration,
                    s.channel_count as usize,
                    s.bin_count as usize,
                )
                .map_err(|e| StageError::failed(format!("factory calibration (seq {}): {e}", input.seq())))?;
                self.factory = Some(f);
            }
            "wheel" => {
                let w: WheelOdometry = input.decode()?;
                if w.distance_m.is_finite() {
                    self.wheel = Some((input.stamp_ns(), w.distance_m, w.speed_mps));
                } else {
                    self.drops.record(
                        Self::NAME,
                        &input,
                        &format_args!("non-finite distance {}", w.distance_m),
                    );
                }
            }
            "sweep" => {
                let s: Sweep = input.decode()?;
                self.sweep(&input, &s, out)?;
            }
            _ => {}
        }
        Ok(())
    }

    fn finish(&mut self, _out: &mut Outputs) -> Result<(), StageError> {
        if self.before_factory > 0 {
            tracing::warn!(
                sweeps = self.before_factory,
                "lgpr_dsp: sweeps before the factory calibration arrived: not processed"
            );
        }
        self.drops.report(Self::NAME);
        Ok(())
    }
}

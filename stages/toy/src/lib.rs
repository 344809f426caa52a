//! Two toy stages that exercise the runtime end to end: [`ToySource`] synthesises
//! radar-like traces, [`ToyGain`] applies a gain to them. The algorithms are the plain
//! functions [`synth_trace`] and [`apply_gain`]; the stages only move messages.

use std::borrow::Cow;

use gprflow_msg::{Header, Message, Samples, Trace};
use gprflow_stage::{
    Input, InputPorts, InputSpec, Output, Outputs, ParamError, PortSpec, Ports, Produce, Stage, StageError,
};

/// Parameters of [`ToySource`].
#[derive(Debug, Clone, serde::Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct ToySourceParams {
    /// Traces to produce (default 100).
    pub count: u64,
    /// Samples per trace (default 201, as the thesis radar).
    pub samples: u32,
    /// Time between traces, seconds (default 0.01).
    pub period_s: f64,
    /// Stamp of the first trace, ns (default 1.7e18, a date in 2023).
    pub start_ns: i64,
    /// Seed of the noise (default 1).
    pub seed: u64,
}

impl Default for ToySourceParams {
    fn default() -> Self {
        Self {
            count: 100,
            samples: 201,
            period_s: 0.01,
            start_ns: 1_700_000_000_000_000_000,
            seed: 1,
        }
    }
}

/// A 500 MHz Ricker pulse at a depth that drifts with the trace index, plus deterministic
/// noise, as raw int16 counts at 0.2 ns per sample.
pub fn synth_trace(index: u64, samples: usize, seed: u64) -> Vec<i16> {
    let mut state = seed ^ index.wrapping_mul(0x9e37_79b9_7f4a_7c15);
    let apex_ns = 8.0 + 4.0 * ((index as f64) * 0.05).sin();
    (0..samples)
        .map(|k| {
            let t_ns = k as f64 * 0.2;
            let a = std::f64::consts::PI * 0.5 * (t_ns - apex_ns);
            let ricker = (1.0 - 2.0 * a * a) * (-a * a).exp();
            // xorshift64*: deterministic per (seed, index, sample)
            state ^= state >> 12;
            state ^= state << 25;
            state ^= state >> 27;
            let noise = ((state.wrapping_mul(0x2545_f491_4f6c_dd1d) >> 40) as f64 / (1u64 << 24) as f64) - 0.5;
            (ricker * 12_000.0 + noise * 200.0).round() as i16
        })
        .collect()
}

/// Synthesises traces.
#[derive(Debug)]
pub struct ToySource {
    params: ToySourceParams,
    next: u64,
    out: Output<Trace<'static>>,
}

impl Stage for ToySource {
    type Params = ToySourceParams;
    const NAME: &'static str = "toy_source";
    const ABOUT: &'static str = "synthesises radar-like int16 traces (a test source)";

    fn outputs(_: &Self::Params) -> Result<Vec<PortSpec>, ParamError> {
        Ok(vec![PortSpec::new("trace", Trace::TYPE_NAME)])
    }

    fn check_params(params: &Self::Params) -> Result<(), ParamError> {
        gprflow_stage::params::non_negative("period_s", params.period_s)
    }

    fn create(params: Self::Params, ports: &Ports) -> Result<Self, StageError> {
        Ok(Self {
            out: ports.output("trace")?,
            params,
            next: 0,
        })
    }

    fn produce(&mut self, out: &mut Outputs) -> Result<Produce, StageError> {
        if self.next >= self.params.count {
            return Ok(Produce::Done);
        }
        let i = self.next;
        let stamp = self.params.start_ns + (i as f64 * self.params.period_s * 1e9).round() as i64;
        let trace = Trace {
            header: Header::new(stamp, "gpr"),
            channel: 0,
            sample_interval_ns: 0.2,
            time_zero_ns: 0.0,
            center_frequency_hz: 5e8,
            distance_m: i as f64 * 0.01,
            samples_i16: Cow::Owned(synth_trace(i, self.params.samples as usize, self.params.seed)),
            ..Trace::default()
        };
        out.send(self.out, &trace)?;
        self.next += 1;
        Ok(Produce::More)
    }
}

/// Parameters of [`ToyGain`].
#[derive(Debug, Clone, serde::Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct ToyGainParams {
    /// Multiplier (default 2.0).
    pub gain: f64,
    /// Added after the gain (default 0.0).
    pub offset: f64,
}

impl Default for ToyGainParams {
    fn default() -> Self {
        Self { gain: 2.0, offset: 0.0 }
    }
}

/// `gain * x + offset` for every sample, as float32.
pub fn apply_gain(samples: Samples<'_>, params: &ToyGainParams) -> Vec<f32> {
    let f = |x: f64| (params.gain * x + params.offset) as f32;
    match samples {
        Samples::I16(s) => s.iter().map(|&x| f(f64::from(x))).collect(),
        Samples::I32(s) => s.iter().map(|&x| f(f64::from(x))).collect(),
        Samples::F32(s) => s.iter().map(|&x| f(f64::from(x))).collect(),
    }
}

/// Applies a gain to traces.
#[derive(Debug)]
pub struct ToyGain {
    params: ToyGainParams,
    out: Output<Trace<'static>>,
}

impl Stage for ToyGain {
    type Params = ToyGainParams;
    const NAME: &'static str = "toy_gain";
    const ABOUT: &'static str = "multiplies trace samples by a gain (a test transformer)";

    fn inputs() -> InputPorts {
        InputPorts::Fixed(vec![InputSpec {
            port: PortSpec::new("trace", Trace::TYPE_NAME),
            optional: false,
        }])
    }

    fn outputs(_: &Self::Params) -> Result<Vec<PortSpec>, ParamError> {
        Ok(vec![PortSpec::new("trace", Trace::TYPE_NAME)])
    }

    fn create(params: Self::Params, ports: &Ports) -> Result<Self, StageError> {
        Ok(Self {
            out: ports.output("trace")?,
            params,
        })
    }

    fn on_message(&mut self, input: Input<'_>, out: &mut Outputs) -> Result<(), StageError> {
        let trace: Trace<'_> = input.decode()?;
        let scaled = Trace {
            header: trace.header.clone(),
            channel: trace.channel,
            sample_interval_ns: trace.sample_interval_ns,
            time_zero_ns: trace.time_zero_ns,
            center_frequency_hz: trace.center_frequency_hz,
            distance_m: trace.distance_m,
            samples_f32: Cow::Owned(apply_gain(trace.samples(), &self.params)),
            ..Trace::default()
        };
        out.send(self.out, &scaled)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn synth_is_deterministic_and_seed_dependent() {
        assert_eq!(synth_trace(3, 201, 1), synth_trace(3, 201, 1));
        assert_ne!(synth_trace(3, 201, 1), synth_trace(3, 201, 2));
        let t = synth_trace(0, 201, 1);
        // the pulse dominates: its peak is near the apex sample (8 ns / 0.2 ns = 40)
        let peak = t
            .iter()
            .enumerate()
            .max_by_key(|(_, v)| v.unsigned_abs())
            .map(|(i, _)| i);
        assert_eq!(peak, Some(40));
    }

    #[test]
    fn gain_scales_every_sample() {
        let p = ToyGainParams { gain: 0.5, offset: 1.0 };
        assert_eq!(apply_gain(Samples::I16(&[2, -4]), &p), vec![2.0, -1.0]);
    }
}

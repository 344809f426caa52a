//! The configurable trace chain of the `dsp` stage (Table 3.1, trace level): stacking, then
//! dewow, zero-time correction, FIR band-pass and SEC gain, in the thesis's order.

use serde::Deserialize;

use crate::trace::{
    Bandpass, BandpassParams, Dewow, DewowParams, SecGain, SecGainParams, StackParams, Stacker, TraceFormat,
    ZeroTimeParams, shift_to_zero_time, zero_time_index,
};
use crate::{Error, Result};

/// Which trace filters run, with their parameters. A step set to `null` (`None`) is skipped;
/// a step given as `{}` takes its defaults. Default: no stacking, all four filters on with
/// their defaults.
#[derive(Clone, Debug, Deserialize, PartialEq)]
#[cfg_attr(feature = "node", derive(schemars::JsonSchema))]
#[serde(deny_unknown_fields, default)]
pub struct ChainParams {
    /// Averaging of consecutive raw traces before the filters (default `None`: off).
    pub stack: Option<StackParams>,
    /// Dewow (default on, one period of the centre frequency).
    pub dewow: Option<DewowParams>,
    /// Zero-time correction at the first negative peak (default on, threshold 0.5).
    pub zero_time: Option<ZeroTimeParams>,
    /// Zero-phase FIR band-pass (default on: 31 taps, 0.5-2 × the centre frequency).
    pub bandpass: Option<BandpassParams>,
    /// SEC gain, eq. 3.1 (default on: a = 0.03, b = 0.7, threshold 80, Gates garage).
    pub sec_gain: Option<SecGainParams>,
}

impl Default for ChainParams {
    fn default() -> Self {
        Self {
            stack: None,
            dewow: Some(DewowParams::default()),
            zero_time: Some(ZeroTimeParams::default()),
            bandpass: Some(BandpassParams::default()),
            sec_gain: Some(SecGainParams::default()),
        }
    }
}

impl ChainParams {
    /// Checks each step that is on, as far as it does not depend on the trace format.
    pub fn check(&self) -> gprflow_params::Result {
        self.stack.as_ref().map_or(Ok(()), StackParams::check)?;
        self.dewow.as_ref().map_or(Ok(()), DewowParams::check)?;
        self.zero_time.as_ref().map_or(Ok(()), ZeroTimeParams::check)?;
        self.bandpass.as_ref().map_or(Ok(()), BandpassParams::check)?;
        self.sec_gain.as_ref().map_or(Ok(()), SecGainParams::check)
    }
}

/// A trace that came out of [`TraceChain::push`].
#[derive(Clone, Copy, Debug)]
pub struct ChainOutput<'a> {
    /// The processed trace.
    pub trace: &'a [f32],
    /// The zero-time shift applied, samples (see [`TraceChain::process`]).
    pub zero_time_index: Option<usize>,
    /// Raw traces averaged into it (1 without stacking).
    pub traces_stacked: usize,
}

/// The trace chain of one radar channel, built once: windows, taps and gains are
/// precomputed and every buffer is allocated in [`TraceChain::new`], so processing a trace
/// allocates nothing.
#[derive(Debug)]
pub struct TraceChain {
    format: TraceFormat,
    stacker: Option<Stacker>,
    dewow: Option<Dewow>,
    zero_time: Option<ZeroTimeParams>,
    bandpass: Option<Bandpass>,
    sec_gain: Option<SecGain>,
    stacked: Vec<f32>,
}

impl TraceChain {
    /// Builds the chain for traces of `samples` samples at `sample_interval_ns` from an
    /// antenna of `center_frequency_hz`; errors name the parameter at fault.
    pub fn new(
        params: &ChainParams,
        samples: usize,
        sample_interval_ns: f64,
        center_frequency_hz: f64,
    ) -> Result<Self> {
        let format = TraceFormat::new(samples, sample_interval_ns, center_frequency_hz);
        format.validate()?;
        if let Some(z) = &params.zero_time {
            z.check()?;
        }
        Ok(Self {
            format,
            stacker: params.stack.as_ref().map(|p| Stacker::new(p, samples)).transpose()?,
            dewow: params.dewow.as_ref().map(|p| Dewow::new(p, &format)).transpose()?,
            zero_time: params.zero_time.clone(),
            bandpass: params
                .bandpass
                .as_ref()
                .map(|p| Bandpass::new(p, &format))
                .transpose()?,
            sec_gain: params.sec_gain.as_ref().map(|p| SecGain::new(p, samples)).transpose()?,
            stacked: vec![0.0; samples],
        })
    }

    /// The trace format the chain was built for.
    pub fn format(&self) -> &TraceFormat {
        &self.format
    }

    /// The band-pass filter, if enabled (its taps, for reports).
    pub fn bandpass(&self) -> Option<&Bandpass> {
        self.bandpass.as_ref()
    }

    /// The SEC gain, if enabled.
    pub fn sec_gain(&self) -> Option<&SecGain> {
        self.sec_gain.as_ref()
    }

    /// Runs the filters on one trace in place (no stacking): dewow, zero time, FIR band-pass,
    /// SEC gain — `y = G ⊙ BP(shift_{k0}(DW(x)))`, `k0` the first negative peak of `DW(x)`.
    ///
    /// Returns `Some(k0)` when the trace was shifted left by `k0` samples (its time zero is
    /// `k0 · dt` after the first sample), `None` when zero-time correction is off or found no
    /// negative peak (the trace is not shifted). Refuses a trace of the wrong length
    /// ([`Error::Size`]) or one holding NaN or an infinity ([`Error::NonFinite`], naming the
    /// first such sample); the trace is then left untouched.
    pub fn process(&mut self, trace: &mut [f32]) -> Result<Option<usize>> {
        self.format.check("trace", trace)?;
        if let Some(index) = trace.iter().position(|v| !v.is_finite()) {
            return Err(Error::NonFinite {
                what: "trace".to_owned(),
                index,
                value: f64::from(trace[index]),
            });
        }
        if let Some(dewow) = &mut self.dewow {
            dewow.apply(trace)?;
        }
        let shift = self.zero_time.as_ref().and_then(|p| zero_time_index(trace, p));
        if let Some(k0) = shift {
            shift_to_zero_time(trace, k0);
        }
        if let Some(bandpass) = &mut self.bandpass {
            bandpass.apply(trace)?;
        }
        if let Some(gain) = &self.sec_gain {
            gain.apply(trace)?;
        }
        Ok(shift)
    }

    /// Feeds one raw trace: stacks it (when stacking is on) and, when a stack completes (every
    /// trace without stacking), runs [`TraceChain::process`] on the mean and returns it.
    pub fn push(&mut self, trace: &[f32]) -> Result<Option<ChainOutput<'_>>> {
        self.format.check("trace", trace)?;
        let traces_stacked = match &mut self.stacker {
            Some(stacker) => {
                let n = stacker.pending() + 1;
                match stacker.push(trace)? {
                    Some(mean) => {
                        self.stacked.copy_from_slice(mean);
                        n
                    }
                    None => return Ok(None),
                }
            }
            None => {
                self.stacked.copy_from_slice(trace);
                1
            }
        };
        let mut stacked = std::mem::take(&mut self.stacked);
        let result = self.process(&mut stacked);
        self.stacked = stacked;
        Ok(Some(ChainOutput {
            trace: &self.stacked,
            zero_time_index: result?,
            traces_stacked,
        }))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn refuses_nan_naming_the_sample() {
        let mut chain = TraceChain::new(&ChainParams::default(), 201, 0.2, 500e6).expect("valid");
        let mut t = vec![0.5_f32; 201];
        t[17] = f32::NAN;
        let before = t.clone();
        match chain.process(&mut t) {
            Err(Error::NonFinite { index, .. }) => assert_eq!(index, 17),
            other => panic!("expected NonFinite, got {other:?}"),
        }
        assert_eq!(t[..17], before[..17]);
        match chain.process(&mut [0.0; 200]) {
            Err(Error::Size { expected, got, .. }) => assert_eq!((expected, got), (201, 200)),
            other => panic!("expected Size, got {other:?}"),
        }
    }

    #[test]
    fn params_parse_with_defaults_and_null_disables() {
        let p: ChainParams =
            serde_json::from_str(r#"{"dewow": null, "bandpass": {"taps": 21}, "stack": {}}"#).expect("parses");
        assert_eq!(p.dewow, None);
        assert_eq!(p.bandpass.as_ref().map(|b| b.taps), Some(21));
        assert_eq!(p.stack, Some(StackParams::default()));
        assert_eq!(p.sec_gain, Some(SecGainParams::default()));
        assert!(serde_json::from_str::<ChainParams>(r#"{"dewo": {}}"#).is_err());
    }

    #[test]
    fn too_many_taps_names_the_key() {
        let p = ChainParams {
            bandpass: Some(BandpassParams {
                taps: 67,
                ..BandpassParams::default()
            }),
            ..ChainParams::default()
        };
        match TraceChain::new(&p, 201, 0.2, 500e6) {
            Err(Error::Param(e)) => assert_eq!(e.key(), "bandpass.taps"),
            other => panic!("expected Param, got {other:?}"),
        }
    }

    #[test]
    fn push_stacks_then_processes() {
        let p = ChainParams {
            stack: Some(StackParams { traces: 3 }),
            ..ChainParams::default()
        };
        let mut chain = TraceChain::new(&p, 201, 0.2, 500e6).expect("valid");
        let t: Vec<f32> = (0..201).map(|k| (k as f32 * 0.3).sin() * 1000.0).collect();
        assert!(chain.push(&t).expect("ok").is_none());
        assert!(chain.push(&t).expect("ok").is_none());
        let out = chain.push(&t).expect("ok").expect("third completes");
        assert_eq!(out.traces_stacked, 3);
        let got = out.trace.to_vec();
        let mut alone = TraceChain::new(&ChainParams::default(), 201, 0.2, 500e6).expect("ok");
        let mut single = t.clone();
        alone.process(&mut single).expect("ok");
        let peak = single.iter().fold(0.0_f32, |m, v| m.max(v.abs()));
        for (a, b) in got.iter().zip(&single) {
            assert!((a - b).abs() <= 1e-5 * peak);
        }
    }
}

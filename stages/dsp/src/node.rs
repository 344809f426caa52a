//! The stages of this crate: `dsp` (the trace chain on every trace) and `dsp_submap` (the
//! window- and image-level filters on every submap). They only move messages; the filters
//! are the library's.

use std::borrow::Cow;

use gprflow_msg::{Message, Samples, Submap, Trace};
use gprflow_stage::{
    Drops, Input, InputPorts, InputSpec, Output, Outputs, ParamError, PortSpec, Ports, Stage, StageError,
};

use crate::chain::{ChainParams, TraceChain};
use crate::image::{GaussianParams, Shape, WaveletDenoiseParams, denoise_wavelet, gaussian_smooth, saliency};
use crate::trace::{BandpassParams, DewowParams, SecGainParams, StackParams, ZeroTimeParams};
use crate::window::{BackgroundModel, subtract_window_mean};
use crate::{Error, Result};

fn single_input(name: &str, ty: &str) -> InputPorts {
    InputPorts::Fixed(vec![InputSpec {
        port: PortSpec::new(name, ty),
        optional: false,
    }])
}

/// Parameters of the `dsp` stage: the trace chain (seed 000 Table 3.1, trace level), each
/// step `null` to skip it.
#[derive(Debug, Clone, serde::Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct DspParams {
    /// Antenna centre frequency, Hz, overriding the traces' own (default: the traces'). Dewow
    /// and the band-pass are tied to it.
    pub center_frequency_hz: Option<f64>,
    /// Replace the first N samples of every raw trace by sample N before anything else
    /// (default 0). GSSI DZT files keep a scan counter and a mark word in samples 0 and 1:
    /// use 2 for them.
    pub hold_first_samples: usize,
    /// Averaging of consecutive raw traces before the filters (default off).
    pub stack: Option<StackParams>,
    /// Dewow (default on).
    pub dewow: Option<DewowParams>,
    /// Zero-time correction at the first negative peak (default on).
    pub zero_time: Option<ZeroTimeParams>,
    /// Zero-phase FIR band-pass (default on).
    pub bandpass: Option<BandpassParams>,
    /// SEC gain, eq. 3.1 (default on: the Gates garage setting).
    pub sec_gain: Option<SecGainParams>,
}

impl Default for DspParams {
    fn default() -> Self {
        let c = ChainParams::default();
        Self {
            center_frequency_hz: None,
            hold_first_samples: 0,
            stack: c.stack,
            dewow: c.dewow,
            zero_time: c.zero_time,
            bandpass: c.bandpass,
            sec_gain: c.sec_gain,
        }
    }
}

impl DspParams {
    fn chain(&self) -> ChainParams {
        ChainParams {
            stack: self.stack.clone(),
            dewow: self.dewow.clone(),
            zero_time: self.zero_time.clone(),
            bandpass: self.bandpass.clone(),
            sec_gain: self.sec_gain.clone(),
        }
    }
}

/// The trace chain on every trace: raw counts in, processed `float32` traces out (time zero at
/// sample 0 where zero-time correction found its peak).
#[derive(Debug)]
pub struct DspStage {
    params: DspParams,
    /// Built from the first trace's format.
    chain: Option<TraceChain>,
    out: Output<Trace<'static>>,
    scratch: Vec<f32>,
    drops: Drops,
    no_zero_time: u64,
}

impl DspStage {
    fn build(&mut self, t: &Trace<'_>) -> std::result::Result<(), StageError> {
        if self.params.hold_first_samples >= t.len() {
            return Err(ParamError::new(
                "hold_first_samples",
                format!(
                    "{} is not below the first trace's {} samples",
                    self.params.hold_first_samples,
                    t.len()
                ),
            )
            .into());
        }
        let fc = self.params.center_frequency_hz.unwrap_or(t.center_frequency_hz);
        let chain = TraceChain::new(&self.params.chain(), t.len(), t.sample_interval_ns, fc).map_err(|e| match e {
            Error::Param(e) => StageError::Params(e),
            other => StageError::failed(format!(
                "the first trace ({} samples, {} ns, centre frequency {fc} Hz) does not suit the chain: {other}",
                t.len(),
                t.sample_interval_ns
            )),
        })?;
        tracing::info!(
            samples = t.len(),
            sample_interval_ns = t.sample_interval_ns,
            center_frequency_hz = fc,
            taps = chain.bandpass().map_or(0, |b| b.taps().len()),
            "dsp: chain built from the first trace"
        );
        self.chain = Some(chain);
        Ok(())
    }
}

impl Stage for DspStage {
    type Params = DspParams;
    const NAME: &'static str = "dsp";
    const ABOUT: &'static str =
        "GPR trace chain: stacking, dewow, zero-time correction, zero-phase FIR band-pass, SEC gain";

    fn inputs() -> InputPorts {
        single_input("trace", Trace::TYPE_NAME)
    }

    fn outputs(_: &Self::Params) -> std::result::Result<Vec<PortSpec>, ParamError> {
        Ok(vec![PortSpec::new("trace", Trace::TYPE_NAME)])
    }

    fn check_params(params: &Self::Params) -> std::result::Result<(), ParamError> {
        gprflow_params::optional(
            "center_frequency_hz",
            params.center_frequency_hz,
            gprflow_params::positive,
        )?;
        params.chain().check()
    }

    fn create(params: Self::Params, ports: &Ports) -> std::result::Result<Self, StageError> {
        Ok(Self {
            params,
            chain: None,
            out: ports.output("trace")?,
            scratch: Vec::new(),
            drops: Drops::new(),
            no_zero_time: 0,
        })
    }

    fn on_message(&mut self, input: Input<'_>, out: &mut Outputs) -> std::result::Result<(), StageError> {
        let t: Trace = input.decode()?;
        if self.chain.is_none() {
            self.build(&t)?;
        }
        self.scratch.clear();
        match t.samples() {
            Samples::F32(s) => self.scratch.extend_from_slice(s),
            Samples::I16(s) => self.scratch.extend(s.iter().map(|&v| f32::from(v))),
            Samples::I32(s) => self.scratch.extend(s.iter().map(|&v| v as f32)),
        }
        let hold = self.params.hold_first_samples;
        if hold > 0 && hold < self.scratch.len() {
            let v = self.scratch[hold];
            self.scratch[..hold].fill(v);
        }
        let Some(chain) = self.chain.as_mut() else {
            return Ok(());
        };
        let fc = chain.format().center_frequency_hz;
        let processed = match chain.push(&self.scratch) {
            Ok(p) => p,
            Err(e @ (Error::Size { .. } | Error::NonFinite { .. })) => {
                self.drops.record(Self::NAME, &input, &e);
                return Ok(());
            }
            Err(e) => return Err(StageError::failed(e)),
        };
        let Some(p) = processed else { return Ok(()) };
        let time_zero_ns = match p.zero_time_index {
            Some(_) => 0.0,
            None => {
                self.no_zero_time += u64::from(self.params.zero_time.is_some());
                t.time_zero_ns
            }
        };
        let msg = Trace {
            header: t.header.clone(),
            channel: t.channel,
            sample_interval_ns: t.sample_interval_ns,
            time_zero_ns,
            center_frequency_hz: fc,
            distance_m: t.distance_m,
            samples_i16: Cow::Borrowed(&[]),
            samples_i32: Cow::Borrowed(&[]),
            samples_f32: Cow::Owned(p.trace.to_vec()),
        };
        out.send(self.out, &msg)
    }

    fn finish(&mut self, _out: &mut Outputs) -> std::result::Result<(), StageError> {
        self.drops.report(Self::NAME);
        if self.no_zero_time > 0 {
            tracing::info!(
                traces = self.no_zero_time,
                "dsp: traces without a negative peak above the threshold: not shifted"
            );
        }
        Ok(())
    }
}

/// Background subtraction of the `dsp_submap` stage.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Deserialize, schemars::JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum Background {
    /// The mean trace over all prior submaps, each trace counted once (the thesis, §3.2.2).
    #[default]
    PriorMean,
    /// Each submap's own mean trace (removes flat layers too; for comparison).
    WindowMean,
    /// None.
    Off,
}

/// Parameters of the `dsp_submap` stage, applied in this order.
#[derive(Debug, Clone, serde::Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct DspSubmapParams {
    /// Background subtraction (default `prior_mean`).
    pub background: Background,
    /// Wavelet denoising, BayesShrink soft threshold (default on, `db1`).
    pub wavelet: Option<WaveletDenoiseParams>,
    /// Gaussian smoothing (default on, 1 px along track).
    pub gaussian: Option<GaussianParams>,
}

impl Default for DspSubmapParams {
    fn default() -> Self {
        Self {
            background: Background::PriorMean,
            wavelet: Some(WaveletDenoiseParams::default()),
            gaussian: Some(GaussianParams::default()),
        }
    }
}

/// Window- and image-level filters on every submap.
#[derive(Debug)]
pub struct DspSubmapStage {
    params: DspSubmapParams,
    background: Option<BackgroundModel>,
    /// End distance of the previous submap (to add only new columns to the background).
    previous_end_m: Option<f64>,
    out: Output<Submap<'static>>,
    drops: Drops,
}

impl DspSubmapStage {
    fn filter(&mut self, m: &mut Submap<'_>) -> Result<()> {
        let shape = Shape {
            rows: m.rows as usize,
            cols: m.cols as usize,
        };
        shape.check("submap pixels", m.pixels.len())?;
        let pixels = m.pixels.to_mut();
        match self.params.background {
            Background::PriorMean => {
                let model = self.background.get_or_insert_with(|| BackgroundModel::new(shape.rows));
                // columns not in the previous submap: consecutive submaps overlap
                let new_cols = match self.previous_end_m {
                    Some(prev) if m.resolution_m > 0.0 => {
                        (((m.end_distance_m - prev).abs() / m.resolution_m).round() as usize).min(shape.cols)
                    }
                    _ => shape.cols,
                };
                let mut column = vec![0.0f32; shape.rows];
                for c in shape.cols - new_cols..shape.cols {
                    for (r, v) in column.iter_mut().enumerate() {
                        *v = pixels[r * shape.cols + c];
                    }
                    model.add_trace(&column)?;
                }
                model.subtract(pixels, shape)?;
            }
            Background::WindowMean => subtract_window_mean(pixels, shape)?,
            Background::Off => {}
        }
        self.previous_end_m = Some(m.end_distance_m);
        if let Some(w) = &self.params.wavelet {
            denoise_wavelet(pixels, shape, w)?;
        }
        if let Some(g) = &self.params.gaussian {
            gaussian_smooth(pixels, shape, g)?;
        }
        m.saliency = saliency(pixels, shape.rows, shape.cols);
        Ok(())
    }
}

impl Stage for DspSubmapStage {
    type Params = DspSubmapParams;
    const NAME: &'static str = "dsp_submap";
    const ABOUT: &'static str = "submap filters: background subtraction (mean trace of all prior submaps), wavelet denoising (BayesShrink), gaussian smoothing";

    fn inputs() -> InputPorts {
        single_input("submap", Submap::TYPE_NAME)
    }

    fn outputs(_: &Self::Params) -> std::result::Result<Vec<PortSpec>, ParamError> {
        Ok(vec![PortSpec::new("submap", Submap::TYPE_NAME)])
    }

    fn check_params(params: &Self::Params) -> std::result::Result<(), ParamError> {
        params.wavelet.as_ref().map_or(Ok(()), WaveletDenoiseParams::check)?;
        params.gaussian.as_ref().map_or(Ok(()), GaussianParams::check)
    }

    fn create(params: Self::Params, ports: &Ports) -> std::result::Result<Self, StageError> {
        Ok(Self {
            params,
            background: None,
            previous_end_m: None,
            out: ports.output("submap")?,
            drops: Drops::new(),
        })
    }

    fn on_message(&mut self, input: Input<'_>, out: &mut Outputs) -> std::result::Result<(), StageError> {
        // `filter` takes the pixels over (`Cow::to_mut`: one copy out of the shared memory)
        let mut m: Submap = input.decode()?;
        match self.filter(&mut m) {
            Ok(()) => {}
            Err(e @ (Error::Size { .. } | Error::NonFinite { .. })) => {
                self.drops
                    .record(Self::NAME, &input, &format_args!("submap {}: {e}", m.id));
                return Ok(());
            }
            Err(e) => return Err(StageError::failed(e)),
        }
        let owned: Submap<'static> = Submap {
            pixels: Cow::Owned(m.pixels.into_owned()),
            column_stamps_ns: Cow::Owned(m.column_stamps_ns.into_owned()),
            header: m.header,
            id: m.id,
            start_stamp: m.start_stamp,
            start_distance_m: m.start_distance_m,
            end_distance_m: m.end_distance_m,
            resolution_m: m.resolution_m,
            sample_interval_ns: m.sample_interval_ns,
            rows: m.rows,
            cols: m.cols,
            start_pose: m.start_pose,
            end_pose: m.end_pose,
            saliency: m.saliency,
            valid: m.valid,
        };
        out.send(self.out, &owned)
    }

    fn finish(&mut self, _out: &mut Outputs) -> std::result::Result<(), StageError> {
        self.drops.report(Self::NAME);
        Ok(())
    }
}

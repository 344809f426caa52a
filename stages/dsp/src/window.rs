//! Window-level background subtraction (Table 3.1: "remove repetitive ringing").
//!
//! A window (submap) is an image `rows x cols`, row-major, rows = samples, cols = traces
//! (see [`crate::image`]). The thesis subtracts "the mean trace over all prior submaps (as
//! opposed to over each submap)" to remove the radar's repeated artifacts while keeping the
//! global, horizontal layering that a per-window mean would erase.
//!
//! Submaps overlap heavily (a new 200-column submap every 0.02 m of a 3 m track), so averaging
//! submaps would count a trace up to ~150 times and weight the middle of the track over its
//! ends. [`BackgroundModel`] therefore takes the traces themselves, each once, as they arrive
//! ([`BackgroundModel::add_trace`]); [`BackgroundModel::subtract`] removes the mean of every
//! trace added so far. Whether the current window counts is the caller's choice, by when it
//! adds the window's new traces: adding them before subtracting (what the `dsp` stage does)
//! includes the current window, so the first window has a background too; subtracting first
//! gives exactly "all prior" traces. With a new window every 0.02 m the two differ by the
//! newest ~0.02 m of track.

use crate::image::{Shape, check_finite};
use crate::trace::check_len;
use crate::{Error, Result};

/// The running mean trace over every trace seen: `b[r] = (1/N) Σ_{i=1}^{N} x_i[r]` (sums in
/// f64).
#[derive(Clone, Debug)]
pub struct BackgroundModel {
    sum: Vec<f64>,
    traces: u64,
    mean: Vec<f32>,
}

impl BackgroundModel {
    /// An empty model for traces of `samples` samples.
    pub fn new(samples: usize) -> Self {
        Self {
            sum: vec![0.0; samples],
            traces: 0,
            mean: vec![0.0; samples],
        }
    }

    /// Adds one trace (once per trace, however many windows it will appear in). Refuses a
    /// trace of the wrong length or with non-finite values.
    pub fn add_trace(&mut self, trace: &[f32]) -> Result<()> {
        check_len("background trace", self.sum.len(), trace.len())?;
        check_finite("background trace", trace)?;
        self.sum.iter_mut().zip(trace).for_each(|(s, &x)| *s += f64::from(x));
        self.traces += 1;
        let inv = 1.0 / self.traces as f64;
        self.mean
            .iter_mut()
            .zip(&self.sum)
            .for_each(|(m, s)| *m = (s * inv) as f32);
        Ok(())
    }

    /// Adds every column of a window as a trace (for windows that do not overlap).
    pub fn add_window(&mut self, window: &[f32], shape: Shape) -> Result<()> {
        self.check_window(window, shape)?;
        let mut column = vec![0.0_f32; shape.rows];
        for c in 0..shape.cols {
            column
                .iter_mut()
                .enumerate()
                .for_each(|(r, v)| *v = window[r * shape.cols + c]);
            self.add_trace(&column)?;
        }
        Ok(())
    }

    /// Traces averaged so far.
    pub fn traces(&self) -> u64 {
        self.traces
    }

    /// The mean trace, `None` before the first trace.
    pub fn mean_trace(&self) -> Option<&[f32]> {
        (self.traces > 0).then_some(&self.mean[..])
    }

    /// `w[r, c] -= b[r]` for every column; no change before the first trace.
    pub fn subtract(&self, window: &mut [f32], shape: Shape) -> Result<()> {
        self.check_window(window, shape)?;
        if let Some(mean) = self.mean_trace() {
            subtract_per_row(window, shape.cols, mean);
        }
        Ok(())
    }

    fn check_window(&self, window: &[f32], shape: Shape) -> Result<()> {
        shape.check("window", window.len())?;
        if shape.rows != self.sum.len() {
            return Err(Error::Size {
                what: "window rows (samples per trace)".to_owned(),
                expected: self.sum.len(),
                got: shape.rows,
            });
        }
        Ok(())
    }
}

fn subtract_per_row(window: &mut [f32], cols: usize, per_row: &[f32]) {
    for (row, &b) in window.chunks_exact_mut(cols.max(1)).zip(per_row) {
        row.iter_mut().for_each(|v| *v -= b);
    }
}

/// The plain per-window background removal, for comparison: `w[r, c] -= (1/C) Σ_c' w[r, c']`
/// (each row's mean over the window's traces; it also removes flat layers). Errors on a size
/// mismatch.
pub fn subtract_window_mean(window: &mut [f32], shape: Shape) -> Result<()> {
    shape.check("window", window.len())?;
    if shape.cols == 0 {
        return Ok(());
    }
    for row in window.chunks_exact_mut(shape.cols) {
        let mean = row.iter().map(|&v| f64::from(v)).sum::<f64>() / shape.cols as f64;
        row.iter_mut().for_each(|v| *v = (f64::from(*v) - mean) as f32);
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn model_averages_each_trace_once() {
        let mut m = BackgroundModel::new(2);
        let shape = Shape::new(2, 3);
        let mut w = vec![1.0, 2.0, 3.0, 10.0, 10.0, 10.0];
        m.subtract(&mut w, shape).expect("ok");
        assert_eq!(w[0], 1.0, "no background yet");
        m.add_trace(&[2.0, 4.0]).expect("ok");
        m.add_trace(&[4.0, 8.0]).expect("ok");
        assert_eq!(m.mean_trace(), Some(&[3.0_f32, 6.0][..]));
        m.subtract(&mut w, shape).expect("ok");
        assert_eq!(w, [-2.0, -1.0, 0.0, 4.0, 4.0, 4.0]);
        assert!(m.add_trace(&[f32::INFINITY, 0.0]).is_err());
        assert!(m.subtract(&mut [0.0; 3], Shape::new(3, 1)).is_err());
    }

    #[test]
    fn window_mean_zeroes_each_row() {
        let mut w = vec![1.0, 2.0, 3.0, 5.0, 5.0, 5.0];
        subtract_window_mean(&mut w, Shape::new(2, 3)).expect("ok");
        assert_eq!(w, [-1.0, 0.0, 1.0, 0.0, 0.0, 0.0]);
    }
}

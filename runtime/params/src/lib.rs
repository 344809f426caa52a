//! Parameter errors and the value checks that stages and their libraries share.
//!
//! A library validates its parameter structs with these checks and returns a
//! [`ParamError`] naming the offending key; a stage's `check_params` calls the same
//! validation, so `gprflow check` reports a bad value at its line in the graph file before
//! anything starts, and the library refuses it the same way when used on its own.
//!
//! ```
//! use gprflow_params::{ParamError, positive};
//!
//! let err = positive("sigma_m", -1.0).unwrap_err();
//! assert_eq!(err.path, ["sigma_m"]);
//! assert_eq!(err.to_string(), "sigma_m: must be a positive number, got -1");
//! // a nested struct's check, seen from its parent
//! assert_eq!(err.within("gate").to_string(), "gate.sigma_m: must be a positive number, got -1");
//! ```

use std::fmt;

/// A parameter error: the path of the offending key inside `params` and what is wrong.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ParamError {
    /// Keys from `params` down to the offending one (empty for the whole map).
    pub path: Vec<String>,
    /// What is wrong, in words.
    pub message: String,
}

impl ParamError {
    /// An error at `key`, a dotted path (`bandpass.taps`) or a single key; empty for the
    /// whole map.
    pub fn new(key: &str, message: impl Into<String>) -> Self {
        let path = if key.is_empty() {
            Vec::new()
        } else {
            key.split('.').map(str::to_owned).collect()
        };
        Self {
            path,
            message: message.into(),
        }
    }

    /// The same error seen from the struct that holds the checked one under `parent`
    /// (a dotted path too).
    #[must_use]
    pub fn within(mut self, parent: &str) -> Self {
        let mut path: Vec<String> = parent.split('.').filter(|k| !k.is_empty()).map(str::to_owned).collect();
        path.append(&mut self.path);
        self.path = path;
        self
    }

    /// The path as one dotted key (`bandpass.taps`).
    pub fn key(&self) -> String {
        self.path.join(".")
    }
}

impl fmt::Display for ParamError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        if self.path.is_empty() {
            write!(f, "{}", self.message)
        } else {
            write!(f, "{}: {}", self.key(), self.message)
        }
    }
}

impl std::error::Error for ParamError {}

/// Result of a parameter check.
pub type Result<T = ()> = std::result::Result<T, ParamError>;

/// `Ok` when `v` is finite (any sign).
///
/// # Errors
/// A [`ParamError`] at `key` otherwise.
pub fn finite(key: &str, v: f64) -> Result {
    if v.is_finite() {
        Ok(())
    } else {
        Err(ParamError::new(key, format!("must be finite, got {v}")))
    }
}

/// `Ok` when `v` is finite and above zero.
///
/// # Errors
/// A [`ParamError`] at `key` otherwise.
pub fn positive(key: &str, v: f64) -> Result {
    if v.is_finite() && v > 0.0 {
        Ok(())
    } else {
        Err(ParamError::new(key, format!("must be a positive number, got {v}")))
    }
}

/// `Ok` when `v` is finite and at least zero.
///
/// # Errors
/// A [`ParamError`] at `key` otherwise.
pub fn non_negative(key: &str, v: f64) -> Result {
    if v.is_finite() && v >= 0.0 {
        Ok(())
    } else {
        Err(ParamError::new(key, format!("must be finite and >= 0, got {v}")))
    }
}

/// `Ok` when `v` is a fraction in (0, 1].
///
/// # Errors
/// A [`ParamError`] at `key` otherwise.
pub fn fraction(key: &str, v: f64) -> Result {
    if v > 0.0 && v <= 1.0 {
        Ok(())
    } else {
        Err(ParamError::new(key, format!("must be in (0, 1], got {v}")))
    }
}

/// `Ok` when `v` is finite and within `[low, high]`.
///
/// # Errors
/// A [`ParamError`] at `key` otherwise.
pub fn within(key: &str, v: f64, low: f64, high: f64) -> Result {
    if v.is_finite() && (low..=high).contains(&v) {
        Ok(())
    } else {
        Err(ParamError::new(key, format!("must be within [{low}, {high}], got {v}")))
    }
}

/// `Ok` when the count `n` is at least `min`.
///
/// # Errors
/// A [`ParamError`] at `key` otherwise.
pub fn at_least(key: &str, n: usize, min: usize) -> Result {
    if n >= min {
        Ok(())
    } else {
        Err(ParamError::new(key, format!("must be at least {min}, got {n}")))
    }
}

/// `Ok` when `v` is `None` or passes `check`: the check of an optional parameter.
///
/// # Errors
/// The check's error.
pub fn optional<T: Copy>(key: &str, v: Option<T>, check: fn(&str, T) -> Result) -> Result {
    v.map_or(Ok(()), |v| check(key, v))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn each_check_refuses_what_it_names_and_accepts_the_rest() {
        for bad in [f64::NAN, f64::INFINITY, f64::NEG_INFINITY] {
            assert!(finite("k", bad).is_err());
            assert!(positive("k", bad).is_err());
            assert!(non_negative("k", bad).is_err());
            assert!(fraction("k", bad).is_err());
            assert!(within("k", bad, -1e9, 1e9).is_err());
        }
        assert!(finite("k", -3.0).is_ok());
        assert!(positive("k", 0.0).is_err() && positive("k", 1e-12).is_ok());
        assert!(non_negative("k", -1e-12).is_err() && non_negative("k", 0.0).is_ok());
        assert!(fraction("k", 0.0).is_err() && fraction("k", 1.0).is_ok() && fraction("k", 1.0 + 1e-12).is_err());
        assert!(within("k", 2.0, 0.0, 2.0).is_ok() && within("k", 2.1, 0.0, 2.0).is_err());
        assert!(at_least("k", 0, 1).is_err() && at_least("k", 1, 1).is_ok());
        assert!(optional("k", None, positive).is_ok());
        assert!(optional("k", Some(-1.0), positive).is_err());
    }

    #[test]
    fn paths_name_the_key_from_the_top() {
        let e = positive("bandpass.taps", 0.0).expect_err("zero is not positive");
        assert_eq!(e.path, ["bandpass", "taps"]);
        assert_eq!(e.clone().within("chain").key(), "chain.bandpass.taps");
        assert_eq!(ParamError::new("", "empty map").to_string(), "empty map");
        assert_eq!(ParamError::new("", "m").within("a").to_string(), "a: m");
    }
}

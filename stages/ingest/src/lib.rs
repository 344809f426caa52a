//! Readers for GPR recordings: CMU-GPR sequence folders ([`cmu`]), GSSI DZT ([`dzt`]),
//! Sensors & Software pulseEKKO DT1/HD ([`dt1`]). Plain code: each reader takes a path and
//! returns values, with errors that name the file, the record and the field.
//!
//! [`mod@format`] tells a source's format from its path. With the feature `node` (default):
//! [`load`] reads a source (or an MCAP recording) into encoded runtime messages, and `node` is
//! the `ingest` stage, which plays them.

pub mod cmu;
pub mod dt1;
pub mod dzt;
pub mod error;
pub mod format;
#[cfg(feature = "node")]
pub mod load;
#[cfg(feature = "node")]
pub mod node;
pub mod radargram;

pub use error::{Error, Result};
pub use format::{SourceFormat, detect};
pub use radargram::{Radargram, RawSamples, RawTrace};

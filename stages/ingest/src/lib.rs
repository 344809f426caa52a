//! Readers for GPR recordings: CMU-GPR sequence folders ([`cmu`]), GSSI DZT ([`dzt`]),
//! Sensors & Software pulseEKKO DT1/HD ([`dt1`]). Plain code: each reader takes a path and
//! returns values, with errors that name the file, the record and the field.
//!
//! `node` (feature `node`, default): the `ingest` stage, which publishes what a reader returns
//! (or an MCAP recording's messages) as runtime messages.

pub mod cmu;
pub mod dt1;
pub mod dzt;
pub mod error;
#[cfg(feature = "node")]
pub mod node;
pub mod radargram;

pub use error::{Error, Result};
pub use radargram::{Radargram, RawSamples, RawTrace};

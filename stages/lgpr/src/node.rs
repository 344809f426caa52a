//! The LGPR stages, the only modules that touch the runtime: `lgpr_dsp` (the sweep chain),
//! `lgpr_map` (a mapping pass into a map store) and `lgpr_track` (localisation against it).

mod dsp;
mod map;
mod track;

pub use self::dsp::LgprDspStage;
pub use self::map::{LgprMapParams, LgprMapStage};
pub use self::track::{LgprTrackParams, LgprTrackStage};

//! The prior map (seed 001 §2.2, §2.2.1): the on-disk store of processed sweeps by position
//! ([`store`]), the local grid interpolated from it around the vehicle ([`grid`]), and the
//! double buffer that grids ahead of the vehicle in the background ([`pager`]).

pub mod grid;
pub mod pager;
pub mod store;

pub use self::grid::{GridSpec, LocalGrid};
pub use self::pager::{GridPager, PagerEvents};
pub use self::store::{Columns, MapInfo, MapReader, MapWriter, StoreError, TileKey, TileRead};

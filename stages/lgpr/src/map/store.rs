//! The prior-map store (seed 001 §2.2: "a database indexed by the geographic location of each
//! sweep"): every channel's column of a processed sweep at its element's world position,
//! in tiles of `tile_m` x `tile_m` (default 50 m), so that a local grid reads only the tiles
//! under it.
//!
//! # Layout (version 1)
//!
//! A map is a directory:
//!
//! - `manifest.json`: `format` (`"gprflow-lgpr-map"`), `version` (1), `tile_m`, `samples`
//!   (per column), `sample_interval_ns`, and what was written so far (`columns`, `length_m`,
//!   `passes`). Written at creation and rewritten by [`MapWriter::finish`].
//! - `tiles/{ix}_{iy}.tile`: the columns whose position falls in
//!   `[ix tile_m, (ix + 1) tile_m) x [iy tile_m, (iy + 1) tile_m)`, as a sequence of blocks
//!   appended in the order written. A block is a 16-byte header, little-endian:
//!   magic `b"LGM1"`, the uncompressed length (u32), the compressed length (u32), the CRC-32
//!   of the compressed bytes (u32); then a zstd frame holding its columns. A column is
//!   `x` (f64, m), `y` (f64, m), `stamp_ns` (i64), `channel` (u16), `scale` (f32) and
//!   `samples` signed bytes; sample `n` is `scale * byte[n]` (8 bits per sample, as the
//!   LGPR's own data product, seed 001 §2.1.3).
//!
//! Blocks are only ever appended, each with one write: a map cut short (a crash, a full disk)
//! keeps every complete block, and a reader reports where a tile stops being readable
//! ([`TileRead::damage`]). Several passes can be written into one map (opened again with
//! [`MapWriter::open`]).

use std::collections::{BTreeMap, HashMap};
use std::fs::{self, File, OpenOptions};
use std::io::{self, Read, Write};
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

/// The `format` of a map's manifest.
pub const FORMAT: &str = "gprflow-lgpr-map";
/// The layout version this crate writes and reads.
pub const VERSION: u32 = 1;
/// Magic at the start of every block.
pub const BLOCK_MAGIC: [u8; 4] = *b"LGM1";
/// Bytes of a block header.
pub const BLOCK_HEADER: usize = 16;
/// Bytes of a column before its samples.
pub const COLUMN_HEADER: usize = 8 + 8 + 8 + 2 + 4;
/// Columns gathered per tile before a block is written.
pub const BLOCK_COLUMNS: usize = 1024;
/// Tiles with unwritten columns kept at once; beyond it the least recently used is written.
const OPEN_TILES: usize = 8;
/// Largest block accepted when reading (uncompressed), bytes: a bad length cannot make the
/// reader allocate without bound.
const MAX_BLOCK_BYTES: usize = 256 << 20;

/// What can go wrong with a map store. Every variant names the file.
#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    /// Reading or writing a file failed.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The failure.
        source: io::Error,
    },
    /// The manifest is not a map manifest.
    #[error("{path}: not a gprflow LGPR map manifest: {message}")]
    Manifest {
        /// The manifest file.
        path: PathBuf,
        /// What is wrong.
        message: String,
    },
    /// The map was written with another layout version.
    #[error("{path}: map layout version {found}, this gprflow reads version {expected}")]
    Version {
        /// The manifest file.
        path: PathBuf,
        /// The version in the file.
        found: u32,
        /// The version this crate reads.
        expected: u32,
    },
    /// Columns do not fit the map (another sample count or interval).
    #[error("{path}: {field}: the map has {map}, the data has {data}")]
    Incompatible {
        /// The manifest file.
        path: PathBuf,
        /// The field that differs.
        field: &'static str,
        /// The map's value.
        map: String,
        /// The new data's value.
        data: String,
    },
    /// A tile ends inside a block.
    #[error(
        "{path}: block {block} at byte {offset} is cut short ({message}); the {good_columns} columns before it are intact"
    )]
    Truncated {
        /// The tile file.
        path: PathBuf,
        /// Index of the bad block in the file.
        block: usize,
        /// Its byte offset.
        offset: u64,
        /// What is missing.
        message: String,
        /// Columns read before it.
        good_columns: usize,
    },
    /// A block's bytes are not what was written.
    #[error(
        "{path}: block {block} at byte {offset} is corrupt ({message}); the {good_columns} columns before it are intact"
    )]
    Corrupt {
        /// The tile file.
        path: PathBuf,
        /// Index of the bad block in the file.
        block: usize,
        /// Its byte offset.
        offset: u64,
        /// What is wrong.
        message: String,
        /// Columns read before it.
        good_columns: usize,
    },
    /// A column to write is not usable.
    #[error("{what}")]
    BadColumn {
        /// What is wrong.
        what: String,
    },
}

fn io_err(path: &Path) -> impl FnOnce(io::Error) -> StoreError + '_ {
    move |source| StoreError::Io {
        path: path.to_owned(),
        source,
    }
}

/// The manifest of a map (`manifest.json`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MapInfo {
    /// Always [`FORMAT`].
    pub format: String,
    /// Layout version ([`VERSION`]).
    pub version: u32,
    /// Tile size, m.
    pub tile_m: f64,
    /// Samples per column.
    pub samples: u32,
    /// Sample interval, ns.
    pub sample_interval_ns: f64,
    /// Columns written (all passes), as of the last [`MapWriter::finish`].
    #[serde(default)]
    pub columns: u64,
    /// Distance driven while mapping (all passes), m.
    #[serde(default)]
    pub length_m: f64,
    /// Passes written.
    #[serde(default)]
    pub passes: u32,
}

impl MapInfo {
    /// A new, empty map's manifest.
    pub fn new(tile_m: f64, samples: u32, sample_interval_ns: f64) -> Self {
        Self {
            format: FORMAT.to_owned(),
            version: VERSION,
            tile_m,
            samples,
            sample_interval_ns,
            columns: 0,
            length_m: 0.0,
            passes: 0,
        }
    }

    /// `Incompatible`, naming `path`, when columns of `samples` samples
    /// `sample_interval_ns` apart do not fit this map.
    fn check_fits(&self, path: PathBuf, samples: u32, sample_interval_ns: f64) -> Result<(), StoreError> {
        if self.samples != samples {
            return Err(StoreError::Incompatible {
                path,
                field: "samples",
                map: self.samples.to_string(),
                data: samples.to_string(),
            });
        }
        if (self.sample_interval_ns - sample_interval_ns).abs() > 1e-6 * sample_interval_ns.abs() {
            return Err(StoreError::Incompatible {
                path,
                field: "sample_interval_ns",
                map: self.sample_interval_ns.to_string(),
                data: sample_interval_ns.to_string(),
            });
        }
        Ok(())
    }

    /// Reads and checks `dir/manifest.json`.
    ///
    /// # Errors
    /// `Io`, `Manifest` (not JSON, another format, a bad tile size), `Version`.
    pub fn read(dir: &Path) -> Result<Self, StoreError> {
        let path = dir.join("manifest.json");
        let text = fs::read_to_string(&path).map_err(io_err(&path))?;
        let value: serde_json::Value = serde_json::from_str(&text).map_err(|e| StoreError::Manifest {
            path: path.clone(),
            message: e.to_string(),
        })?;
        // the version first, so a newer layout's extra fields are reported as a version
        let format = value.get("format").and_then(|v| v.as_str()).unwrap_or_default();
        if format != FORMAT {
            return Err(StoreError::Manifest {
                path,
                message: format!("format is {format:?}, expected {FORMAT:?}"),
            });
        }
        let found = value.get("version").and_then(serde_json::Value::as_u64).unwrap_or(0);
        if found != u64::from(VERSION) {
            return Err(StoreError::Version {
                path,
                found: u32::try_from(found).unwrap_or(u32::MAX),
                expected: VERSION,
            });
        }
        let info: Self = serde_json::from_value(value).map_err(|e| StoreError::Manifest {
            path: path.clone(),
            message: e.to_string(),
        })?;
        if !(info.tile_m.is_finite() && info.tile_m > 0.0) || info.samples == 0 {
            return Err(StoreError::Manifest {
                path,
                message: format!("tile_m {} and samples {} must be positive", info.tile_m, info.samples),
            });
        }
        Ok(info)
    }

    fn write(&self, dir: &Path) -> Result<(), StoreError> {
        let path = dir.join("manifest.json");
        let tmp = dir.join("manifest.json.tmp");
        let text = serde_json::to_string_pretty(self).map_err(|e| StoreError::Manifest {
            path: path.clone(),
            message: e.to_string(),
        })?;
        fs::write(&tmp, text + "\n").map_err(io_err(&tmp))?;
        fs::rename(&tmp, &path).map_err(io_err(&path))
    }

    /// The tile holding world position `(x, y)`.
    pub fn tile_of(&self, x: f64, y: f64) -> TileKey {
        TileKey {
            ix: (x / self.tile_m).floor() as i32,
            iy: (y / self.tile_m).floor() as i32,
        }
    }
}

/// A tile's index: it covers `[ix, ix + 1) x [iy, iy + 1)` tile sizes.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct TileKey {
    /// Column index (x).
    pub ix: i32,
    /// Row index (y).
    pub iy: i32,
}

impl TileKey {
    fn file_name(self) -> String {
        format!("{}_{}.tile", self.ix, self.iy)
    }

    fn parse(name: &str) -> Option<Self> {
        let (ix, iy) = name.strip_suffix(".tile")?.split_once('_')?;
        Some(Self {
            ix: ix.parse().ok()?,
            iy: iy.parse().ok()?,
        })
    }
}

/// Map columns in memory: positions, stamps and channels, and the samples of column `i` at
/// `values[i * samples..(i + 1) * samples]`.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Columns {
    /// Samples per column.
    pub samples: usize,
    /// World `(x, y)` of each column, m.
    pub positions: Vec<[f64; 2]>,
    /// Stamp of the sweep each column came from, ns.
    pub stamps_ns: Vec<i64>,
    /// Channel of each column.
    pub channels: Vec<u16>,
    /// The samples, column after column.
    pub values: Vec<f32>,
}

impl Columns {
    /// No columns, `samples` each.
    pub fn new(samples: usize) -> Self {
        Self {
            samples,
            ..Self::default()
        }
    }

    /// Number of columns.
    pub fn len(&self) -> usize {
        self.positions.len()
    }

    /// No columns.
    pub fn is_empty(&self) -> bool {
        self.positions.is_empty()
    }

    /// The samples of column `i`.
    pub fn column(&self, i: usize) -> &[f32] {
        &self.values[i * self.samples..(i + 1) * self.samples]
    }
}

/// Quantises `samples` to signed bytes: returns the scale (`max |v| / 127`, 0 for an all-zero
/// column) and appends the bytes.
fn quantise(samples: &[f32], out: &mut Vec<u8>) -> f32 {
    let peak = samples.iter().fold(0.0_f32, |m, v| m.max(v.abs()));
    let scale = if peak > 0.0 { peak / 127.0 } else { 0.0 };
    let inv = if scale > 0.0 { 1.0 / scale } else { 0.0 };
    out.extend(
        samples
            .iter()
            .map(|v| ((v * inv).round().clamp(-127.0, 127.0) as i8) as u8),
    );
    scale
}

/// Writes a map: columns are gathered per tile and appended as blocks.
#[derive(Debug)]
pub struct MapWriter {
    dir: PathBuf,
    info: MapInfo,
    /// Unwritten columns per tile (encoded, uncompressed), with the last push that touched it.
    open: HashMap<TileKey, (Vec<u8>, usize, u64)>,
    pushes: u64,
    finished: bool,
}

impl MapWriter {
    /// Creates a new map at `dir` (made if missing; an existing map there is an error).
    ///
    /// # Errors
    /// `Io`; `Manifest` when `dir` already holds a map.
    pub fn create(dir: &Path, info: MapInfo) -> Result<Self, StoreError> {
        let manifest = dir.join("manifest.json");
        if manifest.exists() {
            return Err(StoreError::Manifest {
                path: manifest,
                message: "a map exists here already (open it to add a pass)".into(),
            });
        }
        fs::create_dir_all(dir.join("tiles")).map_err(io_err(dir))?;
        let mut info = info;
        info.passes = 1;
        info.write(dir)?;
        Ok(Self {
            dir: dir.to_owned(),
            info,
            open: HashMap::new(),
            pushes: 0,
            finished: false,
        })
    }

    /// Opens the map at `dir` to add a pass of columns of `samples` samples `sample_interval_ns`
    /// apart, creating it (with `tile_m` tiles) when missing.
    ///
    /// # Errors
    /// As [`MapInfo::read`]; `Incompatible` when the samples differ from the map's.
    pub fn open(dir: &Path, tile_m: f64, samples: u32, sample_interval_ns: f64) -> Result<Self, StoreError> {
        if !dir.join("manifest.json").exists() {
            return Self::create(dir, MapInfo::new(tile_m, samples, sample_interval_ns));
        }
        let mut info = MapInfo::read(dir)?;
        info.check_fits(dir.join("manifest.json"), samples, sample_interval_ns)?;
        info.passes += 1;
        fs::create_dir_all(dir.join("tiles")).map_err(io_err(dir))?;
        info.write(dir)?;
        Ok(Self {
            dir: dir.to_owned(),
            info,
            open: HashMap::new(),
            pushes: 0,
            finished: false,
        })
    }

    /// The manifest as it stands.
    pub fn info(&self) -> &MapInfo {
        &self.info
    }

    /// Adds driven distance to the map's length (for its size per km).
    pub fn add_length(&mut self, metres: f64) {
        if metres.is_finite() && metres > 0.0 {
            self.info.length_m += metres;
        }
    }

    /// Adds every column of the map `from` to this pass (its driven length too): passes
    /// written to a map of their own, such as a pass aligned against this map (the aligned
    /// pass's tracker reads this map while it is written, so it cannot write into it), join
    /// it. `from`'s tiles are read one at a time.
    ///
    /// # Errors
    /// `Incompatible` when `from`'s samples differ; a tile of `from` that cannot be read
    /// whole (`Io`, `Truncated`, `Corrupt`, naming the file: its complete blocks are added
    /// first; the tiles after it are not); `Io` when writing.
    pub fn add_map(&mut self, from: &MapReader) -> Result<u64, StoreError> {
        let theirs = from.info();
        self.info.check_fits(
            from.dir().join("manifest.json"),
            theirs.samples,
            theirs.sample_interval_ns,
        )?;
        let mut added = 0;
        for key in from.tiles()?.into_keys() {
            let read = from.read_tile(key, None)?;
            let c = &read.columns;
            for i in 0..c.len() {
                let [x, y] = c.positions[i];
                self.push(x, y, c.stamps_ns[i], c.channels[i], c.column(i))?;
            }
            added += c.len() as u64;
            if let Some(damage) = read.damage {
                return Err(damage);
            }
        }
        self.add_length(from.info().length_m);
        Ok(added)
    }

    /// Adds one column at world `(x, y)`.
    ///
    /// # Errors
    /// `BadColumn` (wrong length, a non-finite position or sample), `Io` when a block is
    /// written.
    pub fn push(&mut self, x: f64, y: f64, stamp_ns: i64, channel: u16, samples: &[f32]) -> Result<(), StoreError> {
        if samples.len() != self.info.samples as usize {
            return Err(StoreError::BadColumn {
                what: format!("column has {} samples, the map {}", samples.len(), self.info.samples),
            });
        }
        if !(x.is_finite() && y.is_finite()) {
            return Err(StoreError::BadColumn {
                what: format!("column position ({x}, {y}) is not finite"),
            });
        }
        if let Some(n) = samples.iter().position(|v| !v.is_finite()) {
            return Err(StoreError::BadColumn {
                what: format!("channel {channel} sample {n} is {}", samples[n]),
            });
        }
        self.pushes += 1;
        let key = self.info.tile_of(x, y);
        if !self.open.contains_key(&key) && self.open.len() >= OPEN_TILES {
            let oldest = self.open.iter().min_by_key(|(_, (_, _, last))| *last).map(|(k, _)| *k);
            if let Some(k) = oldest {
                self.flush(k)?;
            }
        }
        let pushes = self.pushes;
        let entry = self.open.entry(key).or_insert_with(|| (Vec::new(), 0, pushes));
        let buf = &mut entry.0;
        buf.extend_from_slice(&x.to_le_bytes());
        buf.extend_from_slice(&y.to_le_bytes());
        buf.extend_from_slice(&stamp_ns.to_le_bytes());
        buf.extend_from_slice(&channel.to_le_bytes());
        let at = buf.len();
        buf.extend_from_slice(&[0; 4]);
        let scale = quantise(samples, buf);
        buf[at..at + 4].copy_from_slice(&scale.to_le_bytes());
        entry.1 += 1;
        entry.2 = pushes;
        self.info.columns += 1;
        if entry.1 >= BLOCK_COLUMNS {
            self.flush(key)?;
        }
        Ok(())
    }

    /// Writes tile `key`'s gathered columns as one block.
    fn flush(&mut self, key: TileKey) -> Result<(), StoreError> {
        let Some((raw, _, _)) = self.open.remove(&key) else {
            return Ok(());
        };
        if raw.is_empty() {
            return Ok(());
        }
        let path = self.dir.join("tiles").join(key.file_name());
        let compressed = zstd::bulk::compress(&raw, 3).map_err(io_err(&path))?;
        let too_big = |n: usize| {
            u32::try_from(n).map_err(|_| StoreError::BadColumn {
                what: format!("block of {n} bytes is too large"),
            })
        };
        let mut block = Vec::with_capacity(BLOCK_HEADER + compressed.len());
        block.extend_from_slice(&BLOCK_MAGIC);
        block.extend_from_slice(&too_big(raw.len())?.to_le_bytes());
        block.extend_from_slice(&too_big(compressed.len())?.to_le_bytes());
        block.extend_from_slice(&crc32fast::hash(&compressed).to_le_bytes());
        block.extend_from_slice(&compressed);
        let mut file = OpenOptions::new()
            .create(true)
            .append(true)
            .open(&path)
            .map_err(io_err(&path))?;
        file.write_all(&block).map_err(io_err(&path))
    }

    /// Writes every gathered column and the manifest; returns the manifest.
    ///
    /// # Errors
    /// `Io`.
    pub fn finish(mut self) -> Result<MapInfo, StoreError> {
        self.finish_inner()?;
        Ok(self.info.clone())
    }

    fn finish_inner(&mut self) -> Result<(), StoreError> {
        let keys: Vec<TileKey> = self.open.keys().copied().collect();
        for k in keys {
            self.flush(k)?;
        }
        self.info.write(&self.dir)?;
        self.finished = true;
        Ok(())
    }
}

impl Drop for MapWriter {
    fn drop(&mut self) {
        // a writer dropped without finish (an error upstream) still keeps what it gathered
        if !self.finished
            && let Err(e) = self.finish_inner()
        {
            tracing::warn!("map {}: columns not written: {e}", self.dir.display());
        }
    }
}

/// A tile as read: the columns of every complete block, and what stopped the reading early.
#[derive(Debug, Default)]
pub struct TileRead {
    /// The columns read.
    pub columns: Columns,
    /// Why the rest of the tile could not be read (`Truncated`, `Corrupt`), if so.
    pub damage: Option<StoreError>,
}

/// Reads a map.
#[derive(Debug, Clone)]
pub struct MapReader {
    dir: PathBuf,
    info: MapInfo,
}

impl MapReader {
    /// Opens the map at `dir` (reads and checks the manifest).
    ///
    /// # Errors
    /// As [`MapInfo::read`].
    pub fn open(dir: &Path) -> Result<Self, StoreError> {
        Ok(Self {
            dir: dir.to_owned(),
            info: MapInfo::read(dir)?,
        })
    }

    /// The manifest.
    pub fn info(&self) -> &MapInfo {
        &self.info
    }

    /// The map's directory.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// Every tile on disk with its file size in bytes, by key.
    ///
    /// # Errors
    /// `Io`.
    pub fn tiles(&self) -> Result<BTreeMap<TileKey, u64>, StoreError> {
        let dir = self.dir.join("tiles");
        let mut out = BTreeMap::new();
        for entry in fs::read_dir(&dir).map_err(io_err(&dir))? {
            let entry = entry.map_err(io_err(&dir))?;
            let name = entry.file_name();
            if let Some(key) = name.to_str().and_then(TileKey::parse) {
                let len = entry.metadata().map_err(io_err(&entry.path()))?.len();
                out.insert(key, len);
            }
        }
        Ok(out)
    }

    /// The tiles that intersect `[x0, x1] x [y0, y1]`.
    pub fn tiles_over(&self, x0: f64, y0: f64, x1: f64, y1: f64) -> Vec<TileKey> {
        let a = self.info.tile_of(x0, y0);
        let b = self.info.tile_of(x1, y1);
        let mut out = Vec::new();
        for iy in a.iy..=b.iy {
            for ix in a.ix..=b.ix {
                let key = TileKey { ix, iy };
                if self.dir.join("tiles").join(key.file_name()).exists() {
                    out.push(key);
                }
            }
        }
        out
    }

    /// Reads tile `key` (a missing tile is empty), keeping the columns inside `within`
    /// (`[x0, y0, x1, y1]`) when given.
    ///
    /// # Errors
    /// `Io` when the file cannot be opened or read; damage inside it is in
    /// [`TileRead::damage`].
    pub fn read_tile(&self, key: TileKey, within: Option<[f64; 4]>) -> Result<TileRead, StoreError> {
        let path = self.dir.join("tiles").join(key.file_name());
        let samples = self.info.samples as usize;
        let mut read = TileRead {
            columns: Columns::new(samples),
            damage: None,
        };
        let mut bytes = Vec::new();
        match File::open(&path) {
            Ok(mut f) => {
                f.read_to_end(&mut bytes).map_err(io_err(&path))?;
            }
            Err(e) if e.kind() == io::ErrorKind::NotFound => return Ok(read),
            Err(e) => return Err(io_err(&path)(e)),
        }
        let mut offset = 0;
        let mut block = 0;
        let mut raw = Vec::new();
        while offset < bytes.len() {
            let good_columns = read.columns.len();
            let truncated = |message: String| StoreError::Truncated {
                path: path.clone(),
                block,
                offset: offset as u64,
                message,
                good_columns,
            };
            let corrupt = |message: String| StoreError::Corrupt {
                path: path.clone(),
                block,
                offset: offset as u64,
                message,
                good_columns,
            };
            let rest = &bytes[offset..];
            if rest.len() < BLOCK_HEADER {
                read.damage = Some(truncated(format!("{} of {BLOCK_HEADER} header bytes", rest.len())));
                break;
            }
            if rest[0..4] != BLOCK_MAGIC {
                read.damage = Some(corrupt(format!("magic {:?}, expected {:?}", &rest[0..4], BLOCK_MAGIC)));
                break;
            }
            let word = |i: usize| u32::from_le_bytes([rest[i], rest[i + 1], rest[i + 2], rest[i + 3]]) as usize;
            let (raw_len, comp_len, crc) = (word(4), word(8), word(12) as u32);
            let column_bytes = COLUMN_HEADER + samples;
            if raw_len > MAX_BLOCK_BYTES || raw_len % column_bytes != 0 {
                read.damage = Some(corrupt(format!(
                    "uncompressed length {raw_len} is not a whole number of {column_bytes}-byte columns"
                )));
                break;
            }
            if rest.len() < BLOCK_HEADER + comp_len {
                read.damage = Some(truncated(format!(
                    "{} of {comp_len} compressed bytes",
                    rest.len() - BLOCK_HEADER
                )));
                break;
            }
            let compressed = &rest[BLOCK_HEADER..BLOCK_HEADER + comp_len];
            if crc32fast::hash(compressed) != crc {
                read.damage = Some(corrupt("CRC mismatch".into()));
                break;
            }
            raw.clear();
            raw.resize(raw_len, 0);
            match zstd::bulk::decompress_to_buffer(compressed, &mut raw[..]) {
                Ok(n) if n == raw_len => {}
                Ok(n) => {
                    read.damage = Some(corrupt(format!("{n} bytes decompressed, {raw_len} declared")));
                    break;
                }
                Err(e) => {
                    read.damage = Some(corrupt(format!("zstd: {e}")));
                    break;
                }
            }
            decode_columns(&raw, samples, within, &mut read.columns);
            offset += BLOCK_HEADER + comp_len;
            block += 1;
        }
        Ok(read)
    }
}

/// Appends the columns of one decompressed block (whole columns, checked by the caller).
fn decode_columns(raw: &[u8], samples: usize, within: Option<[f64; 4]>, out: &mut Columns) {
    let f64_at = |b: &[u8], i: usize| {
        f64::from_le_bytes([
            b[i],
            b[i + 1],
            b[i + 2],
            b[i + 3],
            b[i + 4],
            b[i + 5],
            b[i + 6],
            b[i + 7],
        ])
    };
    for c in raw.chunks_exact(COLUMN_HEADER + samples) {
        let x = f64_at(c, 0);
        let y = f64_at(c, 8);
        if let Some([x0, y0, x1, y1]) = within
            && !(x >= x0 && x <= x1 && y >= y0 && y <= y1)
        {
            continue;
        }
        let stamp = i64::from_le_bytes([c[16], c[17], c[18], c[19], c[20], c[21], c[22], c[23]]);
        let channel = u16::from_le_bytes([c[24], c[25]]);
        let scale = f32::from_le_bytes([c[26], c[27], c[28], c[29]]);
        out.positions.push([x, y]);
        out.stamps_ns.push(stamp);
        out.channels.push(channel);
        out.values
            .extend(c[COLUMN_HEADER..].iter().map(|&b| f32::from(b as i8) * scale));
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn column(i: usize, n: usize) -> Vec<f32> {
        (0..n)
            .map(|k| ((i * 7 + k) as f32 * 0.37).sin() * (1.0 + i as f32))
            .collect()
    }

    #[test]
    fn columns_round_trip_within_a_quantisation_step() {
        let dir = tempfile::tempdir().expect("must succeed");
        let mut w = MapWriter::create(dir.path(), MapInfo::new(50.0, 40, 0.163)).expect("must succeed");
        for i in 0..3000 {
            let x = i as f64 * 0.04 - 10.0; // crosses tile x = -1 / 0 / 1 / 2
            w.push(x, 3.0, i as i64, (i % 11) as u16, &column(i, 40))
                .expect("must succeed");
        }
        w.add_length(120.0);
        let info = w.finish().expect("must succeed");
        assert_eq!(info.columns, 3000);
        let r = MapReader::open(dir.path()).expect("must succeed");
        let tiles = r.tiles().expect("must succeed");
        assert_eq!(tiles.keys().map(|k| k.ix).collect::<Vec<_>>(), vec![-1, 0, 1, 2]);
        let mut seen = 0;
        for key in tiles.keys() {
            let t = r.read_tile(*key, None).expect("must succeed");
            assert!(t.damage.is_none());
            for c in 0..t.columns.len() {
                let i = t.columns.stamps_ns[c] as usize;
                let want = column(i, 40);
                let step = want.iter().fold(0.0_f32, |m, v| m.max(v.abs())) / 127.0;
                for (a, b) in t.columns.column(c).iter().zip(&want) {
                    assert!((a - b).abs() <= 0.501 * step, "{a} vs {b}");
                }
                assert_eq!(t.columns.channels[c], (i % 11) as u16);
                seen += 1;
            }
        }
        assert_eq!(seen, 3000);
        // a window keeps only what is inside
        let t = r
            .read_tile(TileKey { ix: 0, iy: 0 }, Some([0.0, 0.0, 10.0, 10.0]))
            .expect("must succeed");
        let inside = (0..3000)
            .map(|i| i as f64 * 0.04 - 10.0)
            .filter(|x| (0.0..=10.0).contains(x))
            .count();
        assert!(t.columns.positions.iter().all(|p| p[0] <= 10.0));
        assert_eq!(t.columns.len(), inside);
    }

    #[test]
    fn a_map_added_to_another_keeps_every_column_bit_for_bit_and_refuses_other_samples() {
        let dir = tempfile::tempdir().expect("must succeed");
        let (a, b, c) = (dir.path().join("a"), dir.path().join("b"), dir.path().join("c"));
        let mut w = MapWriter::create(&a, MapInfo::new(50.0, 40, 0.163)).expect("must succeed");
        for i in 0..1500 {
            w.push(i as f64 * 0.07 - 20.0, 1.0, i as i64, (i % 11) as u16, &column(i, 40))
                .expect("must succeed");
        }
        w.add_length(105.0);
        w.finish().expect("must succeed");
        let mut w = MapWriter::create(&b, MapInfo::new(50.0, 40, 0.163)).expect("must succeed");
        w.push(3.0, 4.0, 7, 2, &column(7, 40)).expect("must succeed");
        w.add_length(1.0);
        w.finish().expect("must succeed");
        // a joins b as its second pass
        let from = MapReader::open(&a).expect("must succeed");
        let mut w = MapWriter::open(&b, 50.0, 40, 0.163).expect("must succeed");
        assert_eq!(w.add_map(&from).expect("must succeed"), 1500);
        let info = w.finish().expect("must succeed");
        assert_eq!((info.columns, info.passes, info.length_m), (1501, 2, 106.0));
        let read_all = |dir: &Path| {
            let r = MapReader::open(dir).expect("must succeed");
            let mut out = Vec::new();
            for key in r.tiles().expect("must succeed").into_keys() {
                let t = r.read_tile(key, None).expect("must succeed");
                assert!(t.damage.is_none());
                for i in 0..t.columns.len() {
                    out.push((
                        t.columns.stamps_ns[i],
                        t.columns.positions[i],
                        t.columns.column(i).to_vec(),
                    ));
                }
            }
            out.sort_by(|x, y| x.partial_cmp(y).expect("finite"));
            out
        };
        let (theirs, joined) = (read_all(&a), read_all(&b));
        assert!(theirs.iter().all(|col| joined.contains(col)));
        // samples of another length are refused by the added map's manifest
        let mut w = MapWriter::create(&c, MapInfo::new(50.0, 16, 0.163)).expect("must succeed");
        let e = w.add_map(&from).expect_err("other samples").to_string();
        assert!(
            e.contains("a/manifest.json") && e.contains("samples: the map has 16, the data has 40"),
            "{e}"
        );
    }

    #[test]
    fn a_cut_tile_keeps_its_complete_blocks_and_says_where() {
        let dir = tempfile::tempdir().expect("must succeed");
        let mut w = MapWriter::create(dir.path(), MapInfo::new(50.0, 16, 0.2)).expect("must succeed");
        for i in 0..(BLOCK_COLUMNS + 100) {
            w.push(1.0, 1.0, i as i64, 0, &column(i, 16)).expect("must succeed");
        }
        w.finish().expect("must succeed");
        let path = dir.path().join("tiles/0_0.tile");
        let len = fs::metadata(&path).expect("must succeed").len();
        let f = OpenOptions::new().write(true).open(&path).expect("must succeed");
        f.set_len(len - 10).expect("must succeed");
        let r = MapReader::open(dir.path()).expect("must succeed");
        let t = r.read_tile(TileKey { ix: 0, iy: 0 }, None).expect("must succeed");
        assert_eq!(t.columns.len(), BLOCK_COLUMNS);
        let e = t.damage.expect("must succeed").to_string();
        assert!(
            e.contains("0_0.tile") && e.contains("block 1") && e.contains("cut short"),
            "{e}"
        );
    }

    #[test]
    fn a_flipped_byte_is_caught_by_the_crc() {
        let dir = tempfile::tempdir().expect("must succeed");
        let mut w = MapWriter::create(dir.path(), MapInfo::new(50.0, 16, 0.2)).expect("must succeed");
        for i in 0..10 {
            w.push(1.0, 1.0, i, 0, &column(i as usize, 16)).expect("must succeed");
        }
        w.finish().expect("must succeed");
        let path = dir.path().join("tiles/0_0.tile");
        let mut bytes = fs::read(&path).expect("must succeed");
        let last = bytes.len() - 1;
        bytes[last] ^= 0x55;
        fs::write(&path, bytes).expect("must succeed");
        let t = MapReader::open(dir.path())
            .expect("must succeed")
            .read_tile(TileKey { ix: 0, iy: 0 }, None)
            .expect("must succeed");
        assert_eq!(t.columns.len(), 0);
        assert!(t.damage.expect("must succeed").to_string().contains("CRC"));
    }

    #[test]
    fn another_version_or_format_is_refused_by_name() {
        let dir = tempfile::tempdir().expect("must succeed");
        MapWriter::create(dir.path(), MapInfo::new(50.0, 16, 0.2))
            .expect("must succeed")
            .finish()
            .expect("must succeed");
        let path = dir.path().join("manifest.json");
        let text = fs::read_to_string(&path)
            .expect("must succeed")
            .replace("\"version\": 1", "\"version\": 7");
        fs::write(&path, text).expect("must succeed");
        let e = MapReader::open(dir.path()).expect_err("must fail").to_string();
        assert!(e.contains("manifest.json") && e.contains("version 7"), "{e}");
        fs::write(&path, "{\"format\": \"something\"}").expect("must succeed");
        let e = MapReader::open(dir.path()).expect_err("must fail").to_string();
        assert!(e.contains("format is \"something\""), "{e}");
        fs::write(&path, "not json").expect("must succeed");
        assert!(
            MapReader::open(dir.path())
                .expect_err("must fail")
                .to_string()
                .contains("not a gprflow LGPR map")
        );
    }

    #[test]
    fn a_second_pass_appends_and_must_match() {
        let dir = tempfile::tempdir().expect("must succeed");
        let mut w = MapWriter::open(dir.path(), 50.0, 16, 0.2).expect("must succeed");
        w.push(1.0, 1.0, 0, 0, &column(0, 16)).expect("must succeed");
        w.finish().expect("must succeed");
        let mut w = MapWriter::open(dir.path(), 50.0, 16, 0.2).expect("must succeed");
        w.push(1.5, 1.0, 1, 0, &column(1, 16)).expect("must succeed");
        let info = w.finish().expect("must succeed");
        assert_eq!((info.passes, info.columns), (2, 2));
        let t = MapReader::open(dir.path())
            .expect("must succeed")
            .read_tile(TileKey { ix: 0, iy: 0 }, None)
            .expect("must succeed");
        assert_eq!(t.columns.len(), 2);
        let e = MapWriter::open(dir.path(), 50.0, 17, 0.2)
            .expect_err("must fail")
            .to_string();
        assert!(e.contains("samples") && e.contains("16") && e.contains("17"), "{e}");
    }

    #[test]
    fn bad_columns_are_refused_before_anything_is_written() {
        let dir = tempfile::tempdir().expect("must succeed");
        let mut w = MapWriter::create(dir.path(), MapInfo::new(50.0, 4, 0.2)).expect("must succeed");
        assert!(w.push(0.0, 0.0, 0, 0, &[0.0; 3]).is_err());
        assert!(w.push(f64::NAN, 0.0, 0, 0, &[0.0; 4]).is_err());
        let e = w
            .push(0.0, 0.0, 0, 3, &[0.0, f32::NAN, 0.0, 0.0])
            .expect_err("must fail")
            .to_string();
        assert!(e.contains("channel 3 sample 1"), "{e}");
        assert_eq!(w.finish().expect("must succeed").columns, 0);
    }
}

//! The double buffer of local grids (seed 001 §2.2.1, Fig. 10): the tracker works on the
//! current grid while a worker thread grids the next one ahead of the vehicle, so a route of
//! any length needs two grids in memory.
//!
//! Policy (for a 50 m grid): once the vehicle has passed the current grid's centre by 5 m along
//! its direction of travel (or is 10 m from it in any direction), the worker grids a new one
//! 15 m ahead; the tracker switches to it once the vehicle is nearer its centre. When the
//! vehicle would leave the current grid's usable part (20 m from its centre) before the next
//! is ready, the tracker waits for it (a stall, counted). At 97 km/h the worker has the 15 m
//! between request and edge, 0.55 s, to grid.

use std::sync::Arc;
use std::sync::mpsc::{Receiver, SyncSender, sync_channel};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use super::grid::{GridSpec, LocalGrid};
use super::store::{MapReader, StoreError};

/// Distance past the grid's centre at which the next grid is requested, in grid sizes
/// (5 m of a 50 m grid).
const TRIGGER: f64 = 0.1;
/// How far ahead of the vehicle the next grid is centred, in grid sizes (15 m).
const LOOKAHEAD: f64 = 0.3;
/// The part of a grid near its edge not used for tracking (the array and the search box must
/// fit inside), in grid sizes (5 m).
const MARGIN: f64 = 0.1;

/// A grid as the worker made it, with how long it took and the damage it met.
#[derive(Debug)]
pub struct Gridded {
    /// The grid.
    pub grid: Arc<LocalGrid>,
    /// Wall time of the gridding.
    pub took: Duration,
    /// Damaged tiles met (their readable part was used).
    pub damage: Vec<StoreError>,
}

/// What the pager did on one update.
#[derive(Debug, Default, Clone, Copy, PartialEq, Eq)]
pub struct PagerEvents {
    /// A new grid was requested.
    pub requested: bool,
    /// The current grid was replaced.
    pub switched: bool,
    /// The tracker had to wait for a grid.
    pub stalled: bool,
}

/// Keeps the current grid and has the next one made in the background.
#[derive(Debug)]
pub struct GridPager {
    spec: GridSpec,
    current: Option<Arc<LocalGrid>>,
    next: Option<Gridded>,
    requests: SyncSender<[f64; 2]>,
    results: Receiver<Result<Gridded, StoreError>>,
    /// Centre of the grid requested and not yet switched to (its grid is in `next` once made).
    next_centre: Option<[f64; 2]>,
    worker: Option<JoinHandle<()>>,
    /// Gridding times, s (for the report).
    pub grid_times_s: Vec<f64>,
    /// Stalls so far.
    pub stalls: u64,
    /// Damage met so far (reported once each by the caller).
    pub damage: Vec<StoreError>,
}

impl GridPager {
    /// A pager on `map` with grids of `spec`, each with the window energies of `window_len`
    /// tabulated ([`LocalGrid::prepare_window`]); starts its worker thread.
    pub fn new(map: MapReader, spec: GridSpec, window_len: usize) -> Self {
        // one request at a time is outstanding (`next_centre`): two slots never block
        let (req_tx, req_rx) = sync_channel::<[f64; 2]>(2);
        let (res_tx, res_rx) = sync_channel(2);
        let worker_spec = spec.clone();
        let worker = std::thread::Builder::new()
            .name("lgpr-grid".into())
            .spawn(move || {
                for centre in req_rx {
                    let start = Instant::now();
                    let out = LocalGrid::from_map_with_window(&map, &worker_spec, centre, window_len).map(
                        |(grid, damage)| Gridded {
                            grid: Arc::new(grid),
                            took: start.elapsed(),
                            damage,
                        },
                    );
                    if res_tx.send(out).is_err() {
                        break;
                    }
                }
            })
            .ok();
        Self {
            spec,
            current: None,
            next: None,
            requests: req_tx,
            results: res_rx,
            next_centre: None,
            worker,
            grid_times_s: Vec::new(),
            stalls: 0,
            damage: Vec::new(),
        }
    }

    /// The grid in use.
    pub fn current(&self) -> Option<&Arc<LocalGrid>> {
        self.current.as_ref()
    }

    fn request(&mut self, centre: [f64; 2]) -> Result<(), StoreError> {
        self.requests.send(centre).map_err(|_| StoreError::BadColumn {
            what: "the gridding thread has stopped".into(),
        })?;
        self.next_centre = Some(centre);
        Ok(())
    }

    fn accept(&mut self, g: Result<Gridded, StoreError>) -> Result<(), StoreError> {
        let mut g = g?;
        self.grid_times_s.push(g.took.as_secs_f64());
        self.damage.append(&mut g.damage);
        self.next = Some(g);
        Ok(())
    }

    fn wait(&mut self) -> Result<(), StoreError> {
        let g = self.results.recv().map_err(|_| StoreError::BadColumn {
            what: "the gridding thread has stopped".into(),
        })?;
        self.accept(g)
    }

    /// Makes the requested grid current, waiting for it when not yet made (`true` then).
    fn switch(&mut self) -> Result<bool, StoreError> {
        let waited = self.next.is_none();
        if waited {
            self.wait()?;
        }
        self.current = self.next.take().map(|g| g.grid);
        self.next_centre = None;
        Ok(waited)
    }

    /// Makes sure a grid covers the vehicle at `position` moving along `direction` (a unit
    /// vector, or zero when stopped), and asks for the next one when due.
    ///
    /// # Errors
    /// Reading the map failed.
    pub fn update(&mut self, position: [f64; 2], direction: [f64; 2]) -> Result<PagerEvents, StoreError> {
        let mut ev = PagerEvents::default();
        if self.next_centre.is_some()
            && self.next.is_none()
            && let Ok(g) = self.results.try_recv()
        {
            self.accept(g)?;
        }
        let Some(current) = self.current.clone() else {
            // the first grid: nothing to track on until it exists
            if self.next_centre.is_none() {
                self.request(position)?;
            }
            self.switch()?;
            ev.switched = true;
            return Ok(ev);
        };
        let size = self.spec.size_m;
        let usable = size / 2.0 - MARGIN * size;
        let here = current.distance_from_centre(position[0], position[1]);
        // the switch is decided on the requested centre, whether or not its grid is ready, so
        // that a run tracks on the same grids however fast it is replayed (a late grid stalls)
        let chebyshev = |c: [f64; 2]| (position[0] - c[0]).abs().max((position[1] - c[1]).abs());
        if self.next_centre.is_some_and(|c| chebyshev(c) < here) {
            ev.stalled = self.switch()?;
            ev.switched = true;
        } else if here > usable {
            // off the usable part with no grid on the way (a jump of the GPS/INS): one here
            if self.next_centre.is_some() {
                if self.next.is_none() {
                    self.wait()?;
                }
                self.next = None;
                self.next_centre = None;
            }
            self.request(position)?;
            self.switch()?;
            ev.requested = true;
            ev.stalled = true;
            ev.switched = true;
        }
        if ev.stalled {
            self.stalls += 1;
        }
        let Some(current) = self.current.clone() else {
            return Ok(ev);
        };
        let c = current.centre();
        let (dx, dy) = (position[0] - c[0], position[1] - c[1]);
        let ahead = dx * direction[0] + dy * direction[1];
        let far = current.distance_from_centre(position[0], position[1]);
        if self.next_centre.is_none() && (ahead > TRIGGER * size || far > 2.0 * TRIGGER * size) {
            let reach = LOOKAHEAD * size;
            self.request([position[0] + reach * direction[0], position[1] + reach * direction[1]])?;
            ev.requested = true;
        }
        Ok(ev)
    }
}

impl Drop for GridPager {
    fn drop(&mut self) {
        // closing the request channel ends the worker
        let (tx, _) = sync_channel(0);
        drop(std::mem::replace(&mut self.requests, tx));
        if let Some(w) = self.worker.take() {
            let _ = w.join();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::map::store::{MapInfo, MapWriter};

    #[test]
    fn a_long_drive_keeps_two_grids_and_never_stalls_at_walking_pace() {
        let dir = tempfile::tempdir().expect("must succeed");
        let mut w = MapWriter::create(dir.path(), MapInfo::new(50.0, 8, 0.2)).expect("must succeed");
        for i in 0..4000 {
            w.push(i as f64 * 0.1, 0.0, i, 0, &[1.0; 8]).expect("must succeed");
        }
        w.finish().expect("must succeed");
        let spec = GridSpec {
            size_m: 20.0,
            ..GridSpec::default()
        };
        let mut pager = GridPager::new(MapReader::open(dir.path()).expect("must succeed"), spec, 4);
        let mut switches = 0;
        for step in 0..3900 {
            let x = step as f64 * 0.1;
            let ev = pager.update([x, 0.0], [1.0, 0.0]).expect("must succeed");
            if ev.switched {
                switches += 1;
            }
            let g = pager.current().expect("must succeed");
            assert!(g.slot_at(x, 0.0).is_some(), "no map under the vehicle at {x}");
            assert!(g.distance_from_centre(x, 0.0) <= 5.0 + 1e-9, "{x} vs {:?}", g.centre());
            // give the worker time, as the time between sweeps would
            if ev.requested {
                std::thread::sleep(Duration::from_millis(20));
            }
        }
        assert!(switches > 20, "{switches}");
        assert!(pager.grid_times_s.len() >= switches - 1);
    }
}

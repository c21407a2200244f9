//! The [`Mapper`]: one map and everything that keeps it up to date — its integrator, its
//! optional distance field and the bookkeeping of the frames it took (sequence, time
//! stamp, sensor position). The service, `replay`, `bench` and the tests insert frames
//! through it and read the map, the field and snapshots from it, so that a feature that
//! changes how a map is kept (a memory budget, pose corrections, decay, deltas) is added
//! here once, not to each caller.
//!
//! ```
//! use voxmap_map::{Frame, FrameStamp, Mapper, MapperConfig, VoxelState};
//! use nalgebra::Isometry3;
//!
//! let mut mapper = Mapper::new(&MapperConfig::default()).unwrap();
//! let points = [[2.0f32, 0.0, 0.0]];
//! let frame = Frame { pose: Isometry3::identity(), points: &points };
//! let report = mapper.insert(&frame, FrameStamp { sequence: 1, stamp_ns: 1_000 }).unwrap();
//! assert_eq!(report.integrate.rays, 1);
//! assert_eq!(mapper.map().state_at(&[2.05, 0.05, 0.05].into()), VoxelState::Occupied);
//! assert_eq!(mapper.last_frame().sequence, 1);
//! ```

mod tiles;

pub use tiles::{SaveReport, StoreConfig, TileReport, TileStats};

use crate::coord::{ConfigError, VoxelCoord, WorldPoint};
use crate::field::{DistanceField, FieldConfig, FieldReport};
use crate::integrate::{
    Frame, IntegrateError, IntegrateReport, Integrator, IntegratorConfig, SetupError,
    MAX_RANGE_VOXELS,
};
use crate::io::mapfile::{self, EncodedMap};
use crate::model::SensorModel;
use crate::occupancy::OccupancyMap;
use crate::snapshot::{Meta, Plan, Scope};
use crate::store::{ExportError, StoreError, StoreParams, TileStore};
use std::path::Path;
use tiles::Tiles;

/// What a [`Mapper`] is made with.
#[derive(Clone, Debug, PartialEq)]
pub struct MapperConfig {
    /// Voxel edge, metres.
    pub resolution: f64,
    pub model: SensorModel,
    pub integrator: IntegratorConfig,
    /// Keep a distance field beside the map, with these settings.
    pub field: Option<FieldConfig>,
}

impl Default for MapperConfig {
    fn default() -> Self {
        Self {
            resolution: 0.1,
            model: SensorModel::default(),
            integrator: IntegratorConfig::default(),
            field: None,
        }
    }
}

/// A frame's place in the sequence the mapper takes: its number and its time stamp
/// (nanoseconds; the frame's own, sensor time).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct FrameStamp {
    pub sequence: u64,
    pub stamp_ns: u64,
}

/// What inserting one frame did.
#[derive(Clone, Debug, PartialEq)]
pub struct InsertReport {
    pub integrate: IntegrateReport,
    /// The distance field's update, when the mapper keeps one.
    pub field: Option<FieldReport>,
    /// Tiles loaded and evicted, when the mapper keeps a tile store.
    pub tiles: Option<TileReport>,
}

/// What became of the distance field when a map was put in ([`Mapper::replace_map`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum FieldAfterLoad {
    /// The mapper keeps no field.
    None,
    /// The field that came with the map, made with the mapper's settings, was taken as it is.
    Carried { band_voxels: u64 },
    /// The field was built anew for the map.
    Rebuilt(FieldReport),
}

/// Why a map was not put in; the mapper is as it was.
#[derive(Clone, Debug, PartialEq)]
#[non_exhaustive]
pub enum ReplaceError {
    /// At the map's resolution the integrator's max range spans more than
    /// [`MAX_RANGE_VOXELS`] voxels.
    RangeTooLong { max_range: f64, resolution: f64 },
    /// The distance field cannot work at the map's resolution.
    Field {
        resolution: f64,
        source: ConfigError,
    },
}

impl std::fmt::Display for ReplaceError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::RangeTooLong {
                max_range,
                resolution,
            } => write!(
                f,
                "at its resolution of {resolution} m, max range {max_range} m spans more than {MAX_RANGE_VOXELS} voxels"
            ),
            Self::Field { resolution, source } => write!(
                f,
                "the distance field cannot work at its resolution of {resolution} m: {source}"
            ),
        }
    }
}

impl std::error::Error for ReplaceError {}

/// One map with its integrator, its optional distance field and its frame bookkeeping.
pub struct Mapper {
    map: OccupancyMap,
    integrator: Integrator,
    field: Option<DistanceField>,
    last: FrameStamp,
    /// The last integrated frame's sensor position.
    sensor: Option<WorldPoint>,
    /// The tile store and the tiles' residency, when the mapper keeps a store.
    tiles: Option<Tiles>,
}

impl Mapper {
    /// An empty map with a new integrator (and field).
    pub fn new(cfg: &MapperConfig) -> Result<Self, SetupError> {
        let map = OccupancyMap::new(cfg.resolution, cfg.model)?;
        Self::with_map(map, cfg.integrator.clone(), cfg.field)
    }

    /// A mapper over `map` (a loaded one, say); its field, if `field` asks for one, is
    /// built from the map.
    pub fn with_map(
        map: OccupancyMap,
        integrator: IntegratorConfig,
        field: Option<FieldConfig>,
    ) -> Result<Self, SetupError> {
        let integrator = Integrator::new(integrator)?;
        let field = field
            .map(|c| DistanceField::new(c, map.resolution()))
            .transpose()?;
        let mut mapper = Mapper {
            map,
            integrator,
            field,
            last: FrameStamp::default(),
            sensor: None,
            tiles: None,
        };
        mapper.rebuild_field();
        Ok(mapper)
    }

    /// Integrate one frame, then bring the distance field up to date around it. On error
    /// nothing has changed.
    pub fn insert(
        &mut self,
        frame: &Frame<'_>,
        stamp: FrameStamp,
    ) -> Result<InsertReport, IntegrateError> {
        let mut tiles = self.tiles.as_ref().map(|_| TileReport::default());
        if let (Some(t), Some(r)) = (&mut self.tiles, &mut tiles) {
            let max_range = self.integrator.config().max_range;
            t.load_for_frame(&mut self.map, self.field.as_mut(), frame, max_range, r);
        }
        let integrate = self.integrator.integrate(&mut self.map, frame)?;
        self.last = stamp;
        let sensor = WorldPoint::from(frame.pose.translation.vector);
        self.sensor = Some(sensor);
        let field = self.field.as_mut().map(|f| {
            let (integ, map) = (&self.integrator, &self.map);
            integ.install(|| f.update(map, integrate.bounds, Some(sensor)))
        });
        if let (Some(t), Some(r)) = (&mut self.tiles, &mut tiles) {
            let working = self.integrator.memory_bytes() as u64;
            let changed = tiles::Changed {
                bounds: integrate.bounds,
                banded: field.and_then(|f| f.transformed),
                sensor,
            };
            t.after_frame(&mut self.map, self.field.as_mut(), changed, working, r);
        }
        Ok(InsertReport {
            integrate,
            field,
            tiles,
        })
    }

    /// Keep the map in a tile store from now on: a new one in `cfg.dir`, or (`resume`)
    /// the one there, whose tiles then load as frames or [`Mapper::load_region`] reach
    /// them, and whose last frame becomes the mapper's. With a memory budget, the map's
    /// resident bytes are kept under it after each frame by evicting tiles to the store.
    /// Refused, changing nothing, where the mapper's map is not empty or the store's map
    /// parameters are not the mapper's (with its distance field's settings, or none: the
    /// field's bands are stored with the tiles).
    pub fn open_store(&mut self, cfg: &StoreConfig) -> Result<(), StoreError> {
        if self.map.grid().leaf_count() > 0 || self.tiles.is_some() {
            return Err(StoreError::Params {
                path: cfg.dir.clone(),
                problem: "a tile store is opened for an empty mapper only".into(),
            });
        }
        let params = self.store_params();
        let (store, stored, last) = if cfg.resume {
            let (store, manifest) = TileStore::open(&cfg.dir)?;
            self.check_store_params(&cfg.dir, &manifest.params)?;
            let stored = (manifest.tiles.iter())
                .map(|e| VoxelCoord::from_array(e.tile))
                .collect();
            let last = FrameStamp {
                sequence: manifest.last_frame.0,
                stamp_ns: manifest.last_frame.1,
            };
            (store, stored, last)
        } else {
            (
                TileStore::create(&cfg.dir, params)?,
                Default::default(),
                self.last,
            )
        };
        self.last = last;
        self.tiles = Some(Tiles::new(store, cfg.memory_budget, stored));
        Ok(())
    }

    /// Continue the tile store in `cfg.dir` (lazily, as [`Mapper::open_store`] with
    /// `resume`) in place of the mapper's map: the map, its field and, with a store, that
    /// store's changes since its last save are dropped (it keeps its last commit).
    /// Refused, changing nothing, where `cfg.dir` holds no store or one of other map
    /// parameters; an I/O error opening it after those checks leaves the mapper empty,
    /// without a store.
    pub fn switch_store(&mut self, cfg: &StoreConfig) -> Result<(), StoreError> {
        let manifest = crate::store::read_manifest(&cfg.dir)?;
        self.check_store_params(&cfg.dir, &manifest.params)?;
        // The old store's threads end before the new one opens: it may be the same
        // directory, whose segments the new store must not share with a live writer.
        self.tiles = None;
        self.clear();
        self.sensor = None;
        self.open_store(&StoreConfig {
            resume: true,
            ..cfg.clone()
        })
    }

    /// The parameters a store of this mapper's map is kept with.
    fn store_params(&self) -> StoreParams {
        StoreParams {
            resolution: self.map.resolution(),
            model: *self.map.model(),
            frac_bits: self.map.quantized().frac_bits,
            field: self.field.as_ref().map(|f| *f.config()),
        }
    }

    /// Refuse a store in `dir` kept with other parameters than this mapper's.
    fn check_store_params(&self, dir: &Path, theirs: &StoreParams) -> Result<(), StoreError> {
        let ours = self.store_params();
        if *theirs == ours {
            return Ok(());
        }
        Err(StoreError::Params {
            path: dir.into(),
            problem: format!("the store's map has {theirs}; this mapper's {ours}"),
        })
    }

    /// Bring back the stored tiles overlapping the world box [lo, hi] (a snapshot's
    /// window, a query's region); nothing without a store.
    pub fn load_region(&mut self, lo: WorldPoint, hi: WorldPoint) -> Option<TileReport> {
        let t = self.tiles.as_mut()?;
        let mut r = TileReport::default();
        let field = self.field.as_mut();
        t.load_box(
            &mut self.map,
            field,
            lo.coords.into(),
            hi.coords.into(),
            &mut r,
        );
        t.adopt_new_nodes(&self.map);
        Some(r)
    }

    /// Save incrementally to the tile store: the tiles changed since their latest record,
    /// then a new manifest. `None` without a store.
    pub fn save_store(&mut self) -> Option<Result<SaveReport, StoreError>> {
        let last = (self.last.sequence, self.last.stamp_ns);
        let t = self.tiles.as_mut()?;
        let (map, field) = (&self.map, self.field.as_ref());
        Some(self.integrator.install(|| t.save(map, field, last)))
    }

    /// Write the map and its field as a map file at `path` (atomically): with a tile
    /// store, every tile, in memory or only in the store, streamed tile by tile; otherwise
    /// as [`Mapper::encode_file`]. The same map and field give the same bytes either way.
    /// Returns the leaves written.
    pub fn write_map_file(&mut self, path: &Path) -> Result<u64, ExportError> {
        match &mut self.tiles {
            Some(t) => t.export(&self.map, self.field.as_ref(), path),
            None => {
                let file = self.encode_file();
                file.write(path)?;
                Ok(self
                    .map
                    .grid()
                    .leaves()
                    .filter(|(_, l)| !l.active.is_empty())
                    .count() as u64)
            }
        }
    }

    /// The tiles' counters, when the mapper keeps a store.
    pub fn tile_stats(&self) -> Option<TileStats> {
        Some(self.tiles.as_ref()?.stats(&self.map, self.field.as_ref()))
    }

    /// The tile store's directory, when the mapper keeps one.
    pub fn store_dir(&self) -> Option<&Path> {
        Some(self.tiles.as_ref()?.store.dir())
    }

    pub fn map(&self) -> &OccupancyMap {
        &self.map
    }

    pub fn field(&self) -> Option<&DistanceField> {
        self.field.as_ref()
    }

    pub fn integrator(&self) -> &Integrator {
        &self.integrator
    }

    /// The last integrated frame's stamp (zeros before any).
    pub fn last_frame(&self) -> FrameStamp {
        self.last
    }

    /// The last integrated frame's sensor position (`None` before any).
    pub fn sensor(&self) -> Option<WorldPoint> {
        self.sensor
    }

    /// Run `f` on the integrator's threads, so that work on the map (snapshot encoding,
    /// saving) keeps to the configured thread count.
    pub fn install<R: Send>(&self, f: impl FnOnce() -> R + Send) -> R {
        self.integrator.install(f)
    }

    /// A snapshot of `scope`, with the distance field when the mapper keeps one: size it
    /// with [`Plan::encoded_len`] and write it with [`Mapper::write_snapshot`].
    pub fn snapshot(&self, scope: Scope, meta: Meta) -> Plan<'_> {
        self.install(|| {
            let plan = Plan::new(&self.map, scope, meta);
            match &self.field {
                Some(f) => plan.with_field(f),
                None => plan,
            }
        })
    }

    /// Write a planned snapshot into `buf` on the integrator's threads.
    pub fn write_snapshot(
        &self,
        plan: &Plan<'_>,
        buf: &mut [u8],
    ) -> Result<usize, crate::snapshot::EncodeError> {
        self.install(|| plan.write(buf))
    }

    /// The map file of the map and its field, encoded on the integrator's threads.
    pub fn encode_file(&self) -> EncodedMap {
        self.install(|| mapfile::encode_map_parts_with(&self.map, self.field.as_ref()))
    }

    /// Forget everything the map holds (and the field, and the tile store's tiles from its
    /// next commit on).
    pub fn clear(&mut self) {
        self.map.clear();
        if let Some(t) = &mut self.tiles {
            t.clear();
        }
        if let Some(f) = &mut self.field {
            f.clear();
        }
    }

    /// Put `map` in place of the mapper's and return the old one. The field the map came
    /// with (`carried`, from its file) is kept if it has the mapper's settings, otherwise
    /// the field is built anew. Refused, changing nothing, where the integrator or the
    /// field cannot work at the map's resolution.
    pub fn replace_map(
        &mut self,
        map: OccupancyMap,
        carried: Option<DistanceField>,
    ) -> Result<(OccupancyMap, FieldAfterLoad), ReplaceError> {
        let resolution = map.resolution();
        if !self.integrator.fits_resolution(resolution) {
            return Err(ReplaceError::RangeTooLong {
                max_range: self.integrator.config().max_range,
                resolution,
            });
        }
        let field = match &self.field {
            None => None,
            Some(ours) => match carried {
                Some(f) if f.config() == ours.config() && f.resolution() == resolution => {
                    Some((f, true))
                }
                _ => Some((
                    DistanceField::new(*ours.config(), resolution)
                        .map_err(|source| ReplaceError::Field { resolution, source })?,
                    false,
                )),
            },
        };
        let old = std::mem::replace(&mut self.map, map);
        let after = match field {
            None => FieldAfterLoad::None,
            Some((f, carried)) => {
                let band_voxels = f.band_voxels();
                self.field = Some(f);
                if carried {
                    FieldAfterLoad::Carried { band_voxels }
                } else {
                    self.rebuild_field()
                }
            }
        };
        Ok((old, after))
    }

    /// Build the field anew from the map as it is.
    fn rebuild_field(&mut self) -> FieldAfterLoad {
        match &mut self.field {
            None => FieldAfterLoad::None,
            Some(f) => {
                let (integ, map, sensor) = (&self.integrator, &self.map, self.sensor);
                FieldAfterLoad::Rebuilt(integ.install(|| f.rebuild(map, sensor)))
            }
        }
    }

    /// The map and its field, the mapper done with.
    pub fn into_parts(self) -> (OccupancyMap, Option<DistanceField>) {
        (self.map, self.field)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::test_rng::Rng;
    use nalgebra::{Isometry3, Translation3, UnitQuaternion};

    fn frames(n: usize) -> Vec<(Isometry3<f64>, Vec<[f32; 3]>)> {
        let mut rng = Rng(11);
        (0..n)
            .map(|i| {
                let pose = Isometry3::from_parts(
                    Translation3::new(0.2 * i as f64, 0.0, 0.5),
                    UnitQuaternion::from_euler_angles(0.0, 0.0, 0.3 * i as f64),
                );
                let pts = (0..3000)
                    .map(|_| {
                        let a = rng.f() * std::f64::consts::TAU;
                        let r = 2.0 + 3.0 * rng.f();
                        [
                            (r * a.cos()) as f32,
                            (r * a.sin()) as f32,
                            rng.f() as f32 - 0.5,
                        ]
                    })
                    .collect();
                (pose, pts)
            })
            .collect()
    }

    fn config(field: bool) -> MapperConfig {
        MapperConfig {
            integrator: IntegratorConfig {
                threads: 2,
                max_range: 8.0,
                pin_threads: false,
                ..Default::default()
            },
            field: field.then(FieldConfig::default),
            ..Default::default()
        }
    }

    #[test]
    fn inserting_equals_integrating_then_updating_the_field() {
        let cfg = config(true);
        let mut mapper = Mapper::new(&cfg).unwrap();
        let mut map = OccupancyMap::new(cfg.resolution, cfg.model).unwrap();
        let mut integ = Integrator::new(cfg.integrator.clone()).unwrap();
        let mut field = DistanceField::new(FieldConfig::default(), cfg.resolution).unwrap();
        for (i, (pose, pts)) in frames(4).iter().enumerate() {
            let frame = Frame {
                pose: *pose,
                points: pts,
            };
            let stamp = FrameStamp {
                sequence: i as u64 + 1,
                stamp_ns: 100 * i as u64,
            };
            let got = mapper.insert(&frame, stamp).unwrap();
            let want = integ.integrate(&mut map, &frame).unwrap();
            let sensor = WorldPoint::from(pose.translation.vector);
            field.update(&map, want.bounds, Some(sensor));
            assert_eq!(got.integrate.rays, want.rays);
            assert!(got.field.is_some());
            assert_eq!(mapper.last_frame(), stamp);
            assert_eq!(mapper.sensor(), Some(sensor));
        }
        assert_eq!(mapfile::encode_map(mapper.map()), mapfile::encode_map(&map));
        let ours = mapper.field().unwrap();
        assert_eq!(ours.band_voxels(), field.band_voxels());
        let a = mapper.encode_file().into_bytes();
        let b = mapfile::encode_map_parts_with(&map, Some(&field)).into_bytes();
        assert_eq!(a, b);
    }

    #[test]
    fn a_rejected_frame_changes_nothing() {
        let mut mapper = Mapper::new(&config(false)).unwrap();
        let (pose, pts) = &frames(1)[0];
        let stamp = FrameStamp {
            sequence: 1,
            stamp_ns: 5,
        };
        mapper
            .insert(
                &Frame {
                    pose: *pose,
                    points: pts,
                },
                stamp,
            )
            .unwrap();
        let before = mapfile::encode_map(mapper.map());
        let mut bad = *pose;
        bad.translation.x = f64::NAN;
        let next = FrameStamp {
            sequence: 2,
            stamp_ns: 6,
        };
        let r = mapper.insert(
            &Frame {
                pose: bad,
                points: pts,
            },
            next,
        );
        assert_eq!(r.unwrap_err(), IntegrateError::NonFinitePose);
        assert_eq!(mapfile::encode_map(mapper.map()), before);
        assert_eq!(mapper.last_frame(), stamp);
    }

    #[test]
    fn a_replaced_map_keeps_a_matching_field_and_rebuilds_another() {
        let cfg = config(true);
        let mut built = Mapper::new(&cfg).unwrap();
        for (i, (pose, pts)) in frames(3).iter().enumerate() {
            let stamp = FrameStamp {
                sequence: i as u64,
                stamp_ns: 0,
            };
            built
                .insert(
                    &Frame {
                        pose: *pose,
                        points: pts,
                    },
                    stamp,
                )
                .unwrap();
        }
        let bytes = built.encode_file().into_bytes();
        let (map, field) = built.into_parts();
        let band = field.as_ref().unwrap().band_voxels();

        let mut m = Mapper::new(&cfg).unwrap();
        let (loaded, carried) = mapfile::decode_map_with_field(&bytes).unwrap();
        let (_, after) = m.replace_map(loaded, carried).unwrap();
        assert_eq!(after, FieldAfterLoad::Carried { band_voxels: band });

        let other = MapperConfig {
            field: Some(FieldConfig {
                max_distance: 1.0,
                ..Default::default()
            }),
            ..cfg.clone()
        };
        let mut m = Mapper::new(&other).unwrap();
        let (loaded, carried) = mapfile::decode_map_with_field(&bytes).unwrap();
        let (_, after) = m.replace_map(loaded, carried).unwrap();
        assert!(matches!(after, FieldAfterLoad::Rebuilt(r) if r.patches > 0));
        assert_eq!(mapfile::encode_map(m.map()), mapfile::encode_map(&map));

        // A map the integrator cannot work at is refused, and the mapper keeps its own.
        let fine = OccupancyMap::new(0.0005, SensorModel::default()).unwrap();
        let err = m.replace_map(fine, None).unwrap_err();
        assert!(matches!(err, ReplaceError::RangeTooLong { .. }), "{err}");
        assert_eq!(mapfile::encode_map(m.map()), mapfile::encode_map(&map));
    }
}

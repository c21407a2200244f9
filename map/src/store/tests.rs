//! The tile store and a mapper under a memory budget: evicted and reloaded maps equal
//! unbudgeted ones byte for byte; saves are incremental and resume; damaged records are
//! refused by name.

use super::record::{self, RecordError};
use super::*;
use crate::coord::WorldPoint;
use crate::integrate::{Frame, IntegratorConfig};
use crate::mapper::{FrameStamp, Mapper, MapperConfig, StoreConfig};
use crate::test_rng::Rng;
use nalgebra::{Isometry3, Translation3, UnitQuaternion};

/// A scratch directory, removed when dropped.
pub(crate) struct Scratch(pub PathBuf);

impl Scratch {
    pub(crate) fn new(name: &str) -> Self {
        static N: std::sync::atomic::AtomicU32 = std::sync::atomic::AtomicU32::new(0);
        let n = N.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        let d =
            std::env::temp_dir().join(format!("voxmap-store-{name}-{}-{n}", std::process::id()));
        let _ = std::fs::remove_dir_all(&d);
        std::fs::create_dir_all(&d).unwrap();
        Self(d)
    }
}

impl Drop for Scratch {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

/// A sensor driven 60 m out along x and back, 2.5 m a frame, seeing walls around it: its
/// tiles (12.8 m) are left behind and reached again on the way back.
fn route() -> Vec<(Isometry3<f64>, Vec<[f32; 3]>)> {
    let mut rng = Rng(5);
    let xs: Vec<f64> = (0..24)
        .map(|i| 2.5 * i as f64)
        .chain((0..24).rev().map(|i| 2.5 * i as f64 + 0.3))
        .collect();
    xs.iter()
        .enumerate()
        .map(|(i, &x)| {
            let pose = Isometry3::from_parts(
                Translation3::new(x, 0.4 * (i % 3) as f64, 1.0),
                UnitQuaternion::from_euler_angles(0.0, 0.0, 0.2 * i as f64),
            );
            let pts = (0..4000)
                .map(|_| {
                    let a = rng.f() * std::f64::consts::TAU;
                    let r = 3.0 + 6.0 * rng.f();
                    [
                        (r * a.cos()) as f32,
                        (r * a.sin()) as f32,
                        (2.0 * rng.f() - 1.0) as f32,
                    ]
                })
                .collect();
            (pose, pts)
        })
        .collect()
}

fn config() -> MapperConfig {
    MapperConfig {
        integrator: IntegratorConfig {
            threads: 2,
            max_range: 7.0,
            pin_threads: false,
            ..Default::default()
        },
        ..Default::default()
    }
}

/// How a test keeps its store in `dir`.
fn store_in(dir: &Path, memory_budget: Option<u64>, resume: bool) -> StoreConfig {
    StoreConfig {
        dir: dir.into(),
        memory_budget,
        resume,
    }
}

/// A mapper keeping a new store in `dir`.
fn with_new_store(dir: &Path, memory_budget: Option<u64>) -> Mapper {
    let mut m = Mapper::new(&config()).unwrap();
    m.open_store(&store_in(dir, memory_budget, false)).unwrap();
    m
}

fn insert_all(m: &mut Mapper, frames: &[(Isometry3<f64>, Vec<[f32; 3]>)]) -> (u32, u32) {
    let (mut loaded, mut evicted) = (0, 0);
    for (i, (pose, pts)) in frames.iter().enumerate() {
        let frame = Frame {
            pose: *pose,
            points: pts,
        };
        let stamp = FrameStamp {
            sequence: i as u64 + 1,
            stamp_ns: 1000 * i as u64,
        };
        let r = m.insert(&frame, stamp).unwrap();
        if let Some(t) = r.tiles {
            assert!(t.refused.is_empty() && t.write_error.is_none(), "{t:?}");
            loaded += t.loaded;
            evicted += t.evicted;
        }
    }
    (loaded, evicted)
}

fn file_of(m: &mut Mapper, dir: &Path, name: &str) -> Vec<u8> {
    let p = dir.join(name);
    m.write_map_file(&p).unwrap();
    std::fs::read(p).unwrap()
}

#[test]
fn a_map_under_a_budget_equals_the_unbudgeted_map_byte_for_byte() {
    let frames = route();
    let out = Scratch::new("out");
    let mut free = Mapper::new(&config()).unwrap();
    insert_all(&mut free, &frames);
    let want = file_of(&mut free, &out.0, "free.vxm");
    let full = free.map().grid().live_bytes() as u64;
    // Half the map: under it after every frame. An eighth: less than one frame's tiles,
    // which are never evicted, so the map exceeds it, and still equals.
    for budget in [full / 2, full / 8] {
        let dir = Scratch::new("budget");
        let mut m = with_new_store(&dir.0, Some(budget));
        let (loaded, evicted) = insert_all(&mut m, &frames);
        assert!(
            evicted > 4 && loaded > 2,
            "budget {budget} of {full}: evicted {evicted}, loaded {loaded}"
        );
        let s = m.tile_stats().unwrap();
        assert!(budget < full / 2 || s.resident_bytes <= budget, "{s:?}");
        assert_eq!(
            file_of(&mut m, &out.0, "budget.vxm"),
            want,
            "budget {budget} of {full}"
        );
        // Saved, then the store alone (exported offline) is the same map.
        let saved = m.save_store().unwrap().unwrap();
        assert!(saved.tiles_written > 0);
        let p = out.0.join("export.vxm");
        export(&dir.0, &p).unwrap();
        assert_eq!(std::fs::read(&p).unwrap(), want);
    }
}

#[test]
fn a_resumed_store_loads_lazily_and_goes_on_as_if_never_stopped() {
    let frames = route();
    let (first, second) = frames.split_at(30);
    let out = Scratch::new("out");
    let mut free = Mapper::new(&config()).unwrap();
    insert_all(&mut free, &frames);
    let want = file_of(&mut free, &out.0, "free.vxm");

    let dir = Scratch::new("resume");
    let cfg = |resume| store_in(&dir.0, None, resume);
    let mut m = Mapper::new(&config()).unwrap();
    m.open_store(&cfg(false)).unwrap();
    insert_all(&mut m, first);
    let a = m.save_store().unwrap().unwrap();
    assert_eq!(a.generation, 1);
    // A second save with nothing changed writes nothing.
    let b = m.save_store().unwrap().unwrap();
    assert_eq!((b.tiles_written, b.generation), (0, 2));
    drop(m);

    // A new store is not made over an existing one.
    let mut again = Mapper::new(&config()).unwrap();
    assert!(matches!(
        again.open_store(&cfg(false)),
        Err(StoreError::Exists(_))
    ));
    let mut m = Mapper::new(&config()).unwrap();
    m.open_store(&cfg(true)).unwrap();
    assert_eq!(
        m.map().grid().leaf_count(),
        0,
        "nothing is loaded before it is needed"
    );
    assert_eq!(m.last_frame().sequence, 30);
    let (loaded, _) = insert_all(&mut m, second);
    assert!(loaded > 0);
    assert_eq!(file_of(&mut m, &out.0, "resumed.vxm"), want);
    // A store of another resolution is refused.
    let mut other = Mapper::new(&MapperConfig {
        resolution: 0.2,
        ..config()
    })
    .unwrap();
    assert!(matches!(
        other.open_store(&cfg(true)),
        Err(StoreError::Params { .. })
    ));
}

#[test]
fn a_damaged_tile_is_refused_by_name_and_its_region_reads_unknown() {
    let frames = route();
    let dir = Scratch::new("damaged");
    let mut m = with_new_store(&dir.0, None);
    insert_all(&mut m, &frames[..10]);
    m.save_store().unwrap().unwrap();
    drop(m);
    let manifest = read_manifest(&dir.0).unwrap();
    let e = manifest.tiles[manifest.tiles.len() / 2];
    let seg = dir.0.join(segment_name(e.segment));
    let mut bytes = std::fs::read(&seg).unwrap();
    bytes[(e.offset + u64::from(e.len) / 2) as usize] ^= 0x10;
    std::fs::write(&seg, &bytes).unwrap();

    let mut m = Mapper::new(&config()).unwrap();
    m.open_store(&store_in(&dir.0, None, true)).unwrap();
    let tile = VoxelCoord::from_array(e.tile);
    let centre = m
        .map()
        .transform()
        .voxel_center(tile + VoxelCoord::new(64, 64, 64));
    let r = m.load_region(centre, centre).unwrap();
    assert_eq!(r.refused.len(), 1);
    assert!(
        r.refused[0].contains(&format!("{:?}", e.tile)),
        "{}",
        r.refused[0]
    );
    assert!(r.refused[0].contains("checksum"), "{}", r.refused[0]);
    assert_eq!(m.tile_stats().unwrap().refused, 1);
    // The other tiles load; the offline export names the bad tile and writes nothing.
    let out = dir.0.join("x.vxm");
    let err = export(&dir.0, &out).unwrap_err().to_string();
    assert!(err.contains(&format!("{:?}", e.tile)), "{err}");
    assert!(!out.exists());
}

#[test]
fn records_refuse_truncation_bit_flips_and_other_versions() {
    let q = crate::model::SensorModel::default().quantize().unwrap();
    let frames = route();
    let mut m = Mapper::new(&config()).unwrap();
    insert_all(&mut m, &frames[..3]);
    let grid = m.map().grid();
    let tile = grid.node_origins().next().unwrap();
    let raw = record::raw_tile(grid, tile, None);
    let n = raw.leaves;
    assert!(n > 10);
    let rec = record::encode(tile, 7, &raw);
    let (head, back) = record::decode(&rec).unwrap();
    assert_eq!((head.tile, head.last_observed, head.leaves), (tile, 7, n));
    assert_eq!(back, raw);
    let decoded = back.decode(tile, &q).unwrap();
    assert_eq!(decoded.leaves.len(), n as usize);
    assert!(decoded.bands.is_empty());
    // A version 1 record (the same bytes, no bands) still reads.
    let mut v1 = rec.clone();
    v1[4] = 1;
    let crc = crc32fast::hash(&v1[..record::HEAD - 4]);
    v1[record::HEAD - 4..record::HEAD].copy_from_slice(&crc.to_le_bytes());
    assert_eq!(record::decode(&v1).unwrap().1, raw);
    for cut in [0, 10, record::HEAD - 1, record::HEAD, rec.len() - 1] {
        assert!(record::decode(&rec[..cut]).is_err(), "cut at {cut}");
    }
    for at in (0..rec.len()).step_by(rec.len() / 97 + 1) {
        let mut bad = rec.clone();
        bad[at] ^= 1;
        assert!(record::decode(&bad).is_err(), "bit flip at {at}");
    }
    let mut v3 = rec.clone();
    v3[4] = 3;
    let crc = crc32fast::hash(&v3[..record::HEAD - 4]);
    v3[record::HEAD - 4..record::HEAD].copy_from_slice(&crc.to_le_bytes());
    assert_eq!(record::decode(&v3).unwrap_err(), RecordError::Version(3));
    // Leaves of another tile are refused.
    let other = tile + VoxelCoord::new(128, 0, 0);
    assert!(raw.decode(other, &q).is_err());
}

#[test]
fn a_damaged_manifest_is_refused() {
    let dir = Scratch::new("manifest");
    let mut m = with_new_store(&dir.0, None);
    insert_all(&mut m, &route()[..2]);
    m.save_store().unwrap().unwrap();
    drop(m);
    let path = dir.0.join(MANIFEST);
    let good = std::fs::read(&path).unwrap();
    for (what, bytes) in [
        ("truncated", good[..good.len() - 3].to_vec()),
        ("bit flip", {
            let mut b = good.clone();
            b[good.len() / 2] ^= 4;
            b
        }),
        ("empty", Vec::new()),
    ] {
        std::fs::write(&path, &bytes).unwrap();
        let e = TileStore::open(&dir.0)
            .err()
            .unwrap_or_else(|| panic!("{what} opened"));
        assert!(matches!(e, StoreError::Manifest { .. }), "{what}: {e}");
    }
}

/// [`config`] with a distance field of `window`.
fn field_config(window: Option<[f64; 3]>) -> MapperConfig {
    MapperConfig {
        field: Some(crate::field::FieldConfig {
            window,
            ..Default::default()
        }),
        ..config()
    }
}

/// The map and field of every tile, the mapper's and its store's, as one map file.
fn whole_with_field(m: &mut Mapper) -> Vec<u8> {
    let far = WorldPoint::new(1e4, 1e4, 1e4);
    let r = m.load_region(-far, far).unwrap();
    assert!(r.refused.is_empty(), "{:?}", r.refused);
    m.encode_file().into_bytes()
}

#[test]
fn a_distance_field_under_a_budget_equals_the_unbudgeted_field() {
    let frames = route();
    // The whole map, then a window that moves with the sensor.
    for window in [None, Some([5.0, 5.0, 2.0])] {
        let cfg = field_config(window);
        let mut free = Mapper::new(&cfg).unwrap();
        insert_all(&mut free, &frames);
        let want = free.encode_file().into_bytes();
        let bands = free.field().unwrap().band_voxels();
        assert!(bands > 10_000, "{bands}");
        let full = (free.map().grid().live_bytes() + free.field().unwrap().memory_bytes()) as u64;
        let dir = Scratch::new("field");
        let mut m = Mapper::new(&cfg).unwrap();
        m.open_store(&store_in(&dir.0, Some(full / 3), false))
            .unwrap();
        let (loaded, evicted) = insert_all(&mut m, &frames);
        assert!(
            evicted > 4 && loaded > 2,
            "window {window:?}: evicted {evicted}, loaded {loaded}"
        );
        let s = m.tile_stats().unwrap();
        assert!(s.resident_bytes < full, "{s:?} of {full}");
        // Streamed from memory and store, the map file with the field is the same bytes.
        let out = Scratch::new("field-out");
        assert!(file_of(&mut m, &out.0, "b.vxm") == file_of(&mut free, &out.0, "f.vxm"));
        assert!(whole_with_field(&mut m) == want, "window {window:?}");
        assert_eq!(m.field().unwrap().band_voxels(), bands);
        drop(m);

        // Saved half way and resumed with the same field: the rest of the frames from the
        // store's state reach the same map and field.
        let dir = Scratch::new("field-resume");
        let store = |resume| store_in(&dir.0, Some(full / 3), resume);
        let mut m = Mapper::new(&cfg).unwrap();
        m.open_store(&store(false)).unwrap();
        insert_all(&mut m, &frames[..30]);
        m.save_store().unwrap().unwrap();
        drop(m);
        let mut back = Mapper::new(&cfg).unwrap();
        back.open_store(&store(true)).unwrap();
        insert_all(&mut back, &frames[30..]);
        assert!(whole_with_field(&mut back) == want, "window {window:?}");
        let resume = store(true);
        // Another field, or none, is refused: the stored bands are this field's.
        for other in [config(), field_config(Some([9.0, 9.0, 9.0]))] {
            let mut m = Mapper::new(&other).unwrap();
            let e = m.open_store(&resume).unwrap_err();
            assert!(e.to_string().contains("distance field"), "{e}");
        }
    }
}

#[test]
fn a_band_record_of_a_leaf_the_record_lacks_is_refused() {
    let q = crate::model::SensorModel::default().quantize().unwrap();
    let mut m = Mapper::new(&field_config(None)).unwrap();
    insert_all(&mut m, &route()[..3]);
    let (grid, field) = (m.map().grid(), m.field().unwrap());
    let tile = (grid.node_origins())
        .max_by_key(|&k| record::raw_tile(grid, k, Some(field)).bytes.len())
        .unwrap();
    let raw = record::raw_tile(grid, tile, Some(field));
    let rec = raw.decode(tile, &q).unwrap();
    assert!(!rec.bands.is_empty());
    // Seeds for the fuzz target (`VOXMAP_FUZZ_SEEDS=fuzz/corpus/store_files`): the
    // smallest tile's record with bands, and a manifest.
    if let Some(d) = std::env::var_os("VOXMAP_FUZZ_SEEDS") {
        // Two obstacles and a free voxel: a record of a few leaves with their bands.
        let mut small = crate::OccupancyMap::new(0.1, Default::default()).unwrap();
        for (v, value) in [([1, 2, 3], 100), ([9, 2, 3], 100), ([5, 5, 5], -10)] {
            small.set_value(VoxelCoord::from_array(v), value);
        }
        let mut f = crate::field::DistanceField::new(*field.config(), 0.1).unwrap();
        f.rebuild(&small, None);
        let tile = VoxelCoord::new(0, 0, 0);
        let raw = record::raw_tile(small.grid(), tile, Some(&f));
        assert!(!raw.split().1.is_empty());
        let d = Path::new(&d);
        std::fs::write(d.join("record-bands"), record::encode(tile, 1, &raw)).unwrap();
        let store = Scratch::new("seed");
        let mut s = with_new_store(&store.0, None);
        insert_all(&mut s, &route()[..2]);
        s.save_store().unwrap().unwrap();
        std::fs::copy(store.0.join(MANIFEST), d.join("manifest")).unwrap();
    }
    // Restored into a new field: the same bands.
    let mut f = crate::field::DistanceField::new(*field.config(), 0.1).unwrap();
    f.restore_tile(&rec.leaves, rec.bands.clone()).unwrap();
    for (o, b) in f.leaves() {
        assert_eq!(Some(b), field.leaf(o));
    }
    // Without its first leaf, the first band (or one out of order) is refused.
    let mut fewer = raw.clone();
    fewer.bytes.drain(..crate::io::mapfile::RECORD);
    fewer.leaves -= 1;
    let first_band = rec.bands[0].0;
    if rec.leaves[0].0 == first_band {
        assert!(fewer.decode(tile, &q).is_err());
    }
    // A band whose obstacles disagree with its leaf (now all free) is refused, changing
    // nothing.
    let mut leaves = rec.leaves.clone();
    let (with_obstacle, ..) = (rec.bands.iter())
        .find(|(_, _, offsets)| offsets.contains(&[0, 0, 0]))
        .unwrap();
    let at = leaves.iter().position(|(o, _)| o == with_obstacle).unwrap();
    leaves[at].1.marked = crate::mask::Mask512::EMPTY;
    let mut g = crate::field::DistanceField::new(*field.config(), 0.1).unwrap();
    let e = g.restore_tile(&leaves, rec.bands).unwrap_err();
    assert!(e.contains("obstacles"), "{e}");
    assert_eq!((g.leaves().count(), g.band_voxels()), (0, 0));
}

#[test]
fn segments_of_mostly_dead_records_are_compacted_away() {
    let frames = route();
    let (out_leg, back) = (&frames[..24], &frames[24..44]);
    let dir = Scratch::new("compact");
    let out = Scratch::new("compact-out");
    let store = |resume| store_in(&dir.0, None, resume);
    let mut m = Mapper::new(&config()).unwrap();
    m.open_store(&store(false)).unwrap();
    insert_all(&mut m, out_leg);
    m.save_store().unwrap().unwrap();
    drop(m);
    let first = read_manifest(&dir.0).unwrap();
    let seg = first.tiles[0].segment;
    assert!(first.tiles.iter().all(|e| e.segment == seg));

    // The way back rewrites most of the first leg's tiles in a new segment.
    let mut m = Mapper::new(&config()).unwrap();
    m.open_store(&store(true)).unwrap();
    insert_all(&mut m, back);
    m.save_store().unwrap().unwrap();
    let after = read_manifest(&dir.0).unwrap();
    let live: u64 = (after.tiles.iter())
        .filter(|e| e.segment == seg)
        .map(|e| u64::from(e.len))
        .sum();
    let size = std::fs::metadata(dir.0.join(segment_name(seg)))
        .unwrap()
        .len();
    assert!(
        live > 0 && 2 * live < size,
        "the first segment is {live} of {size} bytes live"
    );
    // That save handed the first segment's live records to the writer; the next one
    // names none of them and removes it.
    m.save_store().unwrap().unwrap();
    let compacted = read_manifest(&dir.0).unwrap();
    assert!(compacted.tiles.iter().all(|e| e.segment != seg));
    assert!(!dir.0.join(segment_name(seg)).exists());
    assert!(m.tile_stats().unwrap().store.records_copied > 0);
    drop(m);

    // The same map as without a store, from the store alone.
    let mut free = Mapper::new(&config()).unwrap();
    insert_all(&mut free, &frames[..44]);
    let want = file_of(&mut free, &out.0, "free.vxm");
    let p = out.0.join("export.vxm");
    export(&dir.0, &p).unwrap();
    assert!(std::fs::read(&p).unwrap() == want);
}

//! The tile store and a mapper under a memory budget: evicted and reloaded maps equal
//! unbudgeted ones byte for byte; saves are incremental and resume; damaged records are
//! refused by name.

use super::record::{self, RecordError};
use super::*;
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

/// A mapper keeping a new store in `dir`.
fn with_new_store(dir: &Path, memory_budget: Option<u64>) -> Mapper {
    let mut m = Mapper::new(&config()).unwrap();
    m.open_store(&StoreConfig {
        dir: dir.into(),
        memory_budget,
        resume: false,
    })
    .unwrap();
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
    let cfg = |resume| StoreConfig {
        dir: dir.0.clone(),
        memory_budget: None,
        resume,
    };
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
    m.open_store(&StoreConfig {
        dir: dir.0.clone(),
        memory_budget: None,
        resume: true,
    })
    .unwrap();
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
    let (raw, n) = record::raw_tile(grid, tile);
    assert!(n > 10);
    let rec = record::encode(tile, 7, &raw);
    let (head, back) = record::decode(&rec).unwrap();
    assert_eq!((head.tile, head.last_observed, head.leaves), (tile, 7, n));
    assert_eq!(back, raw);
    let leaves = record::leaves_of(&back, tile, &q).unwrap();
    assert_eq!(leaves.len(), n as usize);
    for cut in [0, 10, record::HEAD - 1, record::HEAD, rec.len() - 1] {
        assert!(record::decode(&rec[..cut]).is_err(), "cut at {cut}");
    }
    for at in (0..rec.len()).step_by(rec.len() / 97 + 1) {
        let mut bad = rec.clone();
        bad[at] ^= 1;
        assert!(record::decode(&bad).is_err(), "bit flip at {at}");
    }
    let mut v2 = rec.clone();
    v2[4] = 2;
    let crc = crc32fast::hash(&v2[..record::HEAD - 4]);
    v2[record::HEAD - 4..record::HEAD].copy_from_slice(&crc.to_le_bytes());
    assert_eq!(record::decode(&v2).unwrap_err(), RecordError::Version(2));
    // Leaves of another tile are refused.
    let other = tile + VoxelCoord::new(128, 0, 0);
    assert!(record::leaves_of(&raw, other, &q).is_err());
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

//! `voxmap bench --esdf`: the distance field's costs. Bulk builds over the maps of the
//! paper's frames and of OctoMap's `scan.dat`; per-frame updates over the TUM RGB-D
//! sequence (each frame integrated, then the field brought up to date, as the service
//! does); memory and snapshot bytes per voxel in the band; query times through a snapshot
//! against a state query at the same points.

use super::{median, ms, range_of, shared_dir, BenchArgs};
use anyhow::{Context, Result};
use std::path::{Path, PathBuf};
use std::time::Instant;
use voxmap_map::field::{DistanceField, FieldConfig};
use voxmap_map::io::pcd;
use voxmap_map::snapshot::{FieldView, Meta, Plan, Scope, SnapshotView};
use voxmap_map::{
    Frame, FrameStamp, Integrator, IntegratorConfig, Mapper, MapperConfig, OccupancyMap,
    SensorModel, WorldPoint,
};

pub(super) fn run(a: &BenchArgs, files: &[PathBuf]) -> Result<()> {
    let threads = *a.threads.last().context("--threads is empty")?;
    let cfg = FieldConfig {
        max_distance: a.esdf_max_distance,
        unknown: a.esdf_unknown,
        window: None,
    };
    let integ = |max_range: f64| {
        Integrator::new(IntegratorConfig {
            threads,
            max_range,
            pin_threads: a.pin_threads,
            ..Default::default()
        })
    };
    let probe = integ(30.0)?;
    println!(
        "voxmap bench --esdf: resolution {} m, max distance {} m, unknown {}, {threads} threads, kernel {}, {} timed runs per build (median)",
        a.resolution,
        cfg.max_distance,
        cfg.unknown.name(),
        probe.kernel().name(),
        a.runs
    );
    println!(
        "{:<22} {:>8} {:>10} {:>9} {:>8} {:>8} {:>6} {:>6} {:>6} | {:>10} {:>10} {:>6} {:>7} {:>7} | {:>6} {:>6} {:>6} {:>6} {:>6}",
        "map of", "leaves", "band vox", "build ms", "min", "max", "patches", "B/bv", "used", "snap B", "+field B", "B/bv", "enc ms", "+field",
        "state", "dist", "d+grad", "near", "ratio"
    );
    let mut maps: Vec<(String, OccupancyMap, WorldPoint)> = Vec::new();
    for (name, f) in super::selected(files, a.filter.as_deref()) {
        let cloud = pcd::read(f)?;
        let frame = Frame {
            pose: cloud.pose,
            points: &cloud.points,
        };
        let map = mapped(a, threads, range_of(&name).unwrap_or(30.0), &frame)?;
        let sensor = WorldPoint::from(cloud.pose.translation.vector);
        maps.push((name, map, sensor));
    }
    match scan_dat() {
        Ok(Some(points)) => {
            if let Some(out) = &a.esdf_write_pcd {
                std::fs::create_dir_all(out)?;
                let cloud = pcd::PointCloud {
                    points: points.clone(),
                    pose: nalgebra::Isometry3::identity(),
                };
                pcd::write(&out.join("scan_dat.pcd"), &cloud)?;
            }
            let frame = Frame {
                pose: nalgebra::Isometry3::identity(),
                points: &points,
            };
            let map = mapped(a, threads, 30.0, &frame)?;
            maps.push(("octomap scan.dat".into(), map, WorldPoint::origin()));
        }
        Ok(None) => {}
        Err(e) => println!("(scan.dat skipped: {e:#})"),
    }
    for (name, map, sensor) in &maps {
        bulk_row(a, &probe, cfg, name, map, sensor)?;
    }
    println!(
        "build = the whole field from scratch (as after a load); B/bv = bytes per voxel in the band: the field's heap (tables and allocations as malloc rounds them), used = of it the bands' masks and offsets, then its snapshot section; \
         snap B = the snapshot without, +field B with the field; enc = encode ms without / with; queries: ns per point through the snapshot over 100k points \
         (half within 1 m of an occupied voxel): state_at, distance_at (trilinear), distance_and_gradient_at, nearest_obstacle; ratio = dist / state"
    );
    sequence(a, threads, cfg)
}

/// The map of one frame.
fn mapped(
    a: &BenchArgs,
    threads: usize,
    max_range: f64,
    frame: &Frame<'_>,
) -> Result<OccupancyMap> {
    let mut mapper = mapper(a, threads, max_range, None)?;
    mapper.insert(frame, FrameStamp::default())?;
    Ok(mapper.into_parts().0)
}

/// A mapper of the bench's resolution, with a field of `field`'s settings.
fn mapper(
    a: &BenchArgs,
    threads: usize,
    max_range: f64,
    field: Option<FieldConfig>,
) -> Result<Mapper> {
    Ok(Mapper::new(&MapperConfig {
        resolution: a.resolution,
        model: SensorModel::default(),
        integrator: IntegratorConfig {
            threads,
            max_range,
            pin_threads: a.pin_threads,
            ..Default::default()
        },
        field,
    })?)
}

/// One bulk-build row.
fn bulk_row(
    a: &BenchArgs,
    integ: &Integrator,
    cfg: FieldConfig,
    name: &str,
    map: &OccupancyMap,
    sensor: &WorldPoint,
) -> Result<()> {
    let mut times = Vec::new();
    let mut field = DistanceField::new(cfg, map.resolution())?;
    let mut patches = 0;
    for run in 0..=a.runs {
        let t = Instant::now();
        let r = integ.install(|| field.rebuild(map, Some(*sensor)));
        if run > 0 {
            times.push(ms(t.elapsed()));
        }
        patches = r.patches;
    }
    let med = median(&mut times);
    let band = field.band_voxels();
    let mem_per = field.memory_bytes() as f64 / band.max(1) as f64;
    let used_per = field.leaf_bytes() as f64 / band.max(1) as f64;
    let meta = Meta::default();
    let enc = |with: bool| {
        let mut t = Vec::new();
        let mut bytes = Vec::new();
        for _ in 0..3 {
            let s = Instant::now();
            bytes = integ.install(|| {
                let p = Plan::new(map, Scope::Whole, meta);
                if with {
                    p.with_field(&field).to_vec()
                } else {
                    p.to_vec()
                }
            });
            t.push(ms(s.elapsed()));
        }
        (bytes, median(&mut t))
    };
    let (plain, enc_plain) = enc(false);
    let (with, enc_with) = enc(true);
    let view = SnapshotView::open(&with)?;
    let f = view.distance_field().context("no field in the snapshot")?;
    let section_per = (with.len() - plain.len()) as f64 / band.max(1) as f64;
    let points = query_points(&view);
    let q = query_ns(&view, &f, &points);
    println!(
        "{:<22} {:>8} {:>10} {:>9.2} {:>8.2} {:>8.2} {:>6} {:>6.2} {:>6.2} | {:>10} {:>10} {:>6.2} {:>7.2} {:>7.2} | {:>6.1} {:>6.1} {:>6.1} {:>6.1} {:>6.2}",
        name, map.counts().leaves, band, med, times[0], times[times.len() - 1], patches, mem_per, used_per,
        plain.len(), with.len(), section_per, enc_plain, enc_with, q[0], q[1], q[2], q[3], q[1] / q[0]
    );
    Ok(())
}

/// 100k query points: half within 1 m of an occupied voxel, half anywhere in the bounds.
fn query_points(view: &SnapshotView<'_>) -> Vec<WorldPoint> {
    let mut rng = crate::rng::XorShift::new(7);
    let occupied: Vec<WorldPoint> = view.occupied_centers().take(200_000).collect();
    let (lo, hi) = view.bounds().map_or(([0.0; 3], [1.0; 3]), |(l, h)| {
        let tf = view.transform();
        (
            tf.voxel_center(l).coords.into(),
            tf.voxel_center(h).coords.into(),
        )
    });
    (0..100_000)
        .map(|i| {
            if i % 2 == 0 && !occupied.is_empty() {
                let c = occupied[(rng.next_u64() % occupied.len() as u64) as usize];
                c + nalgebra::Vector3::new(
                    rng.uniform() - 0.5,
                    rng.uniform() - 0.5,
                    rng.uniform() - 0.5,
                ) * 2.0
            } else {
                WorldPoint::new(
                    lo[0] + rng.uniform() * (hi[0] - lo[0]),
                    lo[1] + rng.uniform() * (hi[1] - lo[1]),
                    lo[2] + rng.uniform() * (hi[2] - lo[2]),
                )
            }
        })
        .collect()
}

/// ns per point of state_at, distance_at, distance_and_gradient_at, nearest_obstacle:
/// the median of 5 passes each, alternated.
fn query_ns(view: &SnapshotView<'_>, f: &FieldView<'_>, points: &[WorldPoint]) -> [f64; 4] {
    let mut t: [Vec<f64>; 4] = Default::default();
    let mut sink = 0.0;
    for _ in 0..5 {
        for (k, times) in t.iter_mut().enumerate() {
            let s = Instant::now();
            for p in points {
                sink += match k {
                    0 => view.state_at(p) as u8 as f64,
                    1 => f.distance_at(p).unwrap_or(0.0),
                    2 => f.distance_and_gradient_at(p).map_or(0.0, |(d, g)| d + g.x),
                    _ => match f.nearest_obstacle(p) {
                        voxmap_map::snapshot::Nearest::At { distance, .. } => distance,
                        _ => 0.0,
                    },
                };
            }
            times.push(s.elapsed().as_secs_f64() * 1e9 / points.len() as f64);
        }
    }
    std::hint::black_box(sink);
    t.map(|mut v| median(&mut v))
}

/// OctoMap's `scan.dat` (a real laser scan, `x y z` lines, sensor at the origin), from the
/// shared data, if `bzip2` can unpack it.
fn scan_dat() -> Result<Option<Vec<[f32; 3]>>> {
    let Some(shared) = shared_dir() else {
        return Ok(None);
    };
    let path = shared.join("data/real/octomap/scan.dat.bz2");
    if !path.is_file() {
        return Ok(None);
    }
    let out = std::process::Command::new("bzip2")
        .arg("-dc")
        .arg(&path)
        .output()
        .context("running bzip2")?;
    if !out.status.success() {
        anyhow::bail!("bzip2 -dc {} failed", path.display());
    }
    let text = String::from_utf8_lossy(&out.stdout);
    let points = text
        .lines()
        .filter_map(|l| {
            let v: Vec<f32> = l
                .split_whitespace()
                .filter_map(|w| w.parse().ok())
                .collect();
            (v.len() == 3).then(|| [v[0], v[1], v[2]])
        })
        .collect();
    Ok(Some(points))
}

/// Per-frame updates over the TUM sequence.
fn sequence(a: &BenchArgs, threads: usize, cfg: FieldConfig) -> Result<()> {
    let dir = match &a.esdf_sequence {
        Some(d) => d.clone(),
        None => match shared_dir() {
            Some(s) => s.join("data/real/tum_fr2_pioneer_slam2"),
            None => {
                println!("(no TUM sequence: pass --esdf-sequence DIR)");
                return Ok(());
            }
        },
    };
    let frames = crate::tum::read_frames(&dir, "my_association.txt")?;
    if let Some(out) = &a.esdf_write_pcd {
        write_pcds(out, &frames)?;
    }
    // A depth camera's range: TUM's Kinect reads to about 8 m.
    let max_range = 8.0;
    let mut rows: Vec<(f64, f64)> = Vec::new();
    for run in 0..a.runs.max(1) {
        let mut mapper = mapper(a, threads, max_range, Some(cfg))?;
        for (i, f) in frames.iter().enumerate() {
            let frame = Frame {
                pose: f.pose,
                points: &f.points,
            };
            let stamp = FrameStamp {
                sequence: i as u64 + 1,
                stamp_ns: 0,
            };
            let rep = mapper.insert(&frame, stamp)?;
            let (r, fr) = (rep.integrate, rep.field.expect("the mapper keeps a field"));
            if run == 0 {
                let band = mapper.field().map_or(0, |f| f.band_voxels());
                println!(
                    "tum frame {:>2} {}: {:>7} points, integrate {:>7.2} ms, field {:>7.2} ms ({} leaves changed, {} new, {} patches; {} voxels in the band)",
                    i + 1, f.stamp, f.points.len(), ms(r.times.total()), ms(fr.time), fr.changed_leaves, fr.new_leaves, fr.patches, band
                );
                rows.push((ms(r.times.total()), ms(fr.time)));
            } else {
                rows[i].1 = rows[i].1.min(ms(fr.time));
            }
        }
    }
    if rows.len() > 1 {
        let mut rest: Vec<f64> = rows[1..].iter().map(|r| r.1).collect();
        let first = rows[0].1;
        println!(
            "tum sequence, {} frames, max range {max_range} m: field update median {:.2} ms over frames 2..{} (min over {} runs each), first frame {:.2} ms",
            rows.len(),
            median(&mut rest),
            rows.len(),
            a.runs.max(1),
            first
        );
    }
    Ok(())
}

/// The frames as binary PCD files (pose in VIEWPOINT) in `dir/tum`, for other tools on the
/// same data.
fn write_pcds(dir: &Path, frames: &[crate::tum::DepthFrame]) -> Result<()> {
    let dir = dir.join("tum");
    std::fs::create_dir_all(&dir)?;
    for f in frames {
        let cloud = pcd::PointCloud {
            points: f.points.clone(),
            pose: f.pose,
        };
        let p = dir.join(format!("{}.pcd", f.stamp));
        pcd::write(&p, &cloud).with_context(|| p.display().to_string())?;
    }
    println!("wrote {} frames to {}", frames.len(), dir.display());
    Ok(())
}

//! `voxmap bench --mission`: a long drive through the procedural city (`sim::city`), the
//! map kept without a budget and under `--memory-budget` with a tile store, each run in a
//! process of its own (peak RSS is per process), alternated: the frames' p50/p99, the peak
//! RSS, the tiles' traffic, and whether the two final maps are the same bytes.

use super::BenchArgs;
use crate::os::peak_rss;
use crate::rng::XorShift;
use crate::sim::city::{City, Route};
use crate::sim::Lidar;
use anyhow::{bail, Context, Result};
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Instant;
use voxmap_map::field::FieldConfig;
use voxmap_map::mapper::StoreConfig;
use voxmap_map::{Frame, FrameStamp, IntegratorConfig, Mapper, MapperConfig, RayMode};

/// Sensor height above the street (m) and the map's max range (m).
const HEIGHT: f64 = 1.8;
const MAX_RANGE: f64 = 20.0;

/// The parent: the two runs as child processes, `rounds` times alternated, then the table.
pub(super) fn run(a: &BenchArgs) -> Result<()> {
    let dir = match &a.mission_dir {
        Some(d) => d.clone(),
        None => std::env::temp_dir().join(format!("voxmap-mission-{}", std::process::id())),
    };
    std::fs::create_dir_all(&dir)?;
    let route = Route {
        blocks: a.mission_blocks,
        height: HEIGHT,
    };
    println!(
        "voxmap bench --mission: {} frames of a 64-beam LiDAR (65,536 rays, seen to 30 m) along a {:.0} m loop of the city's streets, back to the start; 0.1 m, max range {MAX_RANGE} m, exact, {} threads{}; budget {}; scratch {}",
        a.mission_frames,
        route.length(),
        threads(a)?,
        if a.mission_esdf { ", a 2 m distance field" } else { "" },
        a.memory_budget,
        dir.display()
    );
    let exe = std::env::current_exe()?;
    let mut files: Vec<(String, PathBuf)> = Vec::new();
    for round in 0..a.mission_rounds {
        for budget in ["unlimited", a.memory_budget.as_str()] {
            let run_dir = dir.join(format!("{round}-{budget}"));
            let _ = std::fs::remove_dir_all(&run_dir);
            std::fs::create_dir_all(&run_dir)?;
            let out = Command::new(&exe)
                .args(["bench", "--mission", "--mission-child"])
                .args(["--memory-budget", budget])
                .args(["--mission-frames", &a.mission_frames.to_string()])
                .args(["--mission-blocks", &a.mission_blocks.to_string()])
                .args(["--threads", &threads(a)?.to_string()])
                .args(["--pin-threads", &a.pin_threads.to_string()])
                .args(if a.mission_esdf {
                    &["--mission-esdf"][..]
                } else {
                    &[]
                })
                .arg("--mission-dir")
                .arg(&run_dir)
                .output()?;
            if !out.status.success() {
                bail!(
                    "mission run ({budget}) failed: {}",
                    String::from_utf8_lossy(&out.stderr)
                );
            }
            let line = String::from_utf8_lossy(&out.stdout);
            println!("  round {round}, budget {budget:>9}: {}", line.trim());
            files.push((budget.to_string(), run_dir.join("map.vxm")));
        }
    }
    let first = std::fs::read(&files[0].1)?;
    let same = files
        .iter()
        .map(|(_, f)| std::fs::read(f).map(|b| b == first))
        .collect::<std::io::Result<Vec<bool>>>()?;
    println!(
        "  final maps byte-identical across all runs: {} ({} bytes, md5 {})",
        if same.iter().all(|&s| s) { "yes" } else { "NO" },
        first.len(),
        md5_hex(&files[0].1)
    );
    if a.mission_dir.is_none() {
        let _ = std::fs::remove_dir_all(&dir);
    }
    Ok(())
}

fn threads(a: &BenchArgs) -> Result<usize> {
    a.threads.last().copied().context("--threads is empty")
}

fn md5_hex(p: &Path) -> String {
    Command::new("md5sum")
        .arg(p)
        .output()
        .ok()
        .and_then(|o| String::from_utf8(o.stdout).ok())
        .and_then(|s| s.split_whitespace().next().map(str::to_string))
        .unwrap_or_else(|| "?".into())
}

/// A child: one drive, its numbers on one line.
pub(super) fn child(a: &BenchArgs) -> Result<()> {
    let dir = a
        .mission_dir
        .clone()
        .context("--mission-child needs --mission-dir")?;
    let budget = crate::config::parse_bytes(&a.memory_budget)?;
    let cfg = MapperConfig {
        resolution: 0.1,
        integrator: IntegratorConfig {
            threads: threads(a)?,
            max_range: MAX_RANGE,
            mode: RayMode::Exact,
            pin_threads: a.pin_threads,
        },
        field: a.mission_esdf.then(FieldConfig::default),
        ..Default::default()
    };
    let mut mapper = Mapper::new(&cfg)?;
    if budget.is_some() {
        mapper.open_store(&StoreConfig {
            dir: dir.join("store"),
            memory_budget: budget,
            resume: false,
        })?;
    }
    let route = Route {
        blocks: a.mission_blocks,
        height: HEIGHT,
    };
    let city = City::new(42);
    let mut lidar = Lidar::os0_64();
    lidar.max_range = 30.0;
    let mut rng = XorShift::new(7);
    let mut pts = Vec::new();
    let mut ms = Vec::with_capacity(a.mission_frames);
    let (mut points, mut loaded, mut evicted) = (0u64, 0u64, 0u64);
    let start = Instant::now();
    for k in 0..a.mission_frames {
        let pose = route.pose(k as f64 * route.length() / a.mission_frames as f64);
        lidar.scan(&city, &pose, &mut rng, &mut pts);
        let frame = Frame { pose, points: &pts };
        let stamp = FrameStamp {
            sequence: k as u64 + 1,
            stamp_ns: k as u64 * 100_000_000,
        };
        let t = Instant::now();
        let r = mapper.insert(&frame, stamp)?;
        ms.push(t.elapsed().as_secs_f64() * 1e3);
        points += pts.len() as u64;
        if let Some(t) = r.tiles {
            if let Some(e) = t.refused.first().or(t.write_error.as_ref()) {
                bail!("frame {k}: {e}");
            }
            loaded += u64::from(t.loaded);
            evicted += u64::from(t.evicted);
        }
    }
    let wall = start.elapsed().as_secs_f64();
    let rss_drive = peak_rss().unwrap_or(0);
    let field_bytes = mapper.field().map_or(0, |f| f.memory_bytes()) as u64;
    let resident = mapper
        .tile_stats()
        .map_or(mapper.map().grid().live_bytes() as u64 + field_bytes, |t| {
            t.resident_bytes
        });
    let working = mapper.integrator().memory_bytes() as u64;
    let worst_wait = mapper
        .tile_stats()
        .map_or(0.0, |t| t.worst_wait.as_secs_f64() * 1e3);
    let t = Instant::now();
    let leaves = mapper.write_map_file(&dir.join("map.vxm"))?;
    let export_s = t.elapsed().as_secs_f64();
    // The store committed, for `voxmap inspect` (not timed).
    if let Some(r) = mapper.save_store() {
        r?;
    }
    let mut sorted = ms.clone();
    sorted.sort_by(f64::total_cmp);
    let q = |p| crate::quantile::percentile(&sorted, p);
    let total: f64 = ms.iter().sum();
    println!(
        "frames {} p50 {:.2} ms p99 {:.2} ms max {:.2} ms, {:.2} Mpoints/s; peak RSS {} MiB (drive), {} MiB (with the export); map {} MiB resident (field {} MiB), integrator {} MiB, {} leaves; tiles loaded {loaded} evicted {evicted}, worst wait {worst_wait:.2} ms; export {export_s:.1} s; wall {wall:.0} s",
        ms.len(),
        q(0.5),
        q(0.99),
        sorted.last().copied().unwrap_or(0.0),
        points as f64 / (total / 1e3) / 1e6,
        rss_drive >> 20,
        peak_rss().unwrap_or(0) >> 20,
        resident >> 20,
        field_bytes >> 20,
        working >> 20,
        leaves
    );
    Ok(())
}

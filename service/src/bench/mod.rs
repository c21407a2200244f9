//! `voxmap bench`: integration speed and map quality on the paper's synthetic workloads,
//! side by side with the paper's numbers.

mod e2e;
mod esdf;
mod mission;

use anyhow::{bail, Context, Result};
use clap::Args;
use std::path::{Path, PathBuf};
use std::time::Instant;
use voxmap_map::integrate::PhaseTimes;
use voxmap_map::io::pcd;
use voxmap_map::{
    Frame, FrameStamp, IntegratorConfig, Mapper, MapperConfig, OccupancyMap, RayMode, SensorModel,
    VoxelState,
};

#[derive(Args, Debug)]
pub struct BenchArgs {
    /// Directory of workload PCD files (default: generate the paper's workloads with
    /// shared/bench/gen_workloads.py into a cache directory).
    #[arg(long)]
    workloads: Option<PathBuf>,
    /// Timed runs per row, each into a fresh map (after one untimed warm-up run).
    #[arg(long, default_value_t = 5)]
    runs: usize,
    /// Thread counts, comma separated.
    #[arg(long, default_value = "1,2", value_delimiter = ',')]
    threads: Vec<usize>,
    /// Ray modes, comma separated: exact, subsample, bundle, unique_end.
    #[arg(
        long,
        default_value = "exact,subsample,bundle,unique_end",
        value_delimiter = ','
    )]
    modes: Vec<String>,
    /// Only workloads whose name contains this.
    #[arg(long)]
    filter: Option<String>,
    #[arg(long, default_value_t = 0.1)]
    resolution: f64,
    /// Sub-cells per voxel edge for the subsample mode.
    #[arg(long, default_value_t = 2)]
    subsample_factor: u32,
    /// Bundle size above which one mean ray is cast.
    #[arg(long, default_value_t = 4)]
    bundle_threshold: u32,
    /// One JSON object per line instead of a table.
    #[arg(long)]
    json: bool,
    /// Skip the snapshot measurements (run on the exact map at the last thread count).
    #[arg(long)]
    no_snapshot: bool,
    /// Pin integration thread i to the i-th CPU, as the service does by default (for
    /// `--e2e`, the service's).
    #[arg(long, default_value_t = true, action = clap::ArgAction::Set)]
    pin_threads: bool,
    /// Instead: the end-to-end benchmark (service, sensor and planner processes) with
    /// phases of this many seconds.
    #[arg(long, value_name = "SECONDS")]
    e2e: Option<f64>,
    /// With --e2e: compare the service without and with `--ros2` (alternated, normal
    /// scheduling), for what encoding and publishing the ROS 2 map topics costs.
    #[arg(long, requires = "e2e")]
    e2e_ros2: bool,
    /// With --e2e: compare the service without and with `--esdf` (alternated, normal
    /// scheduling): the latency from a frame to a readable distance field.
    #[arg(long, requires = "e2e")]
    e2e_esdf: bool,
    /// Instead: the distance field benchmark (bulk builds over the workloads' maps and
    /// OctoMap's scan.dat, per-frame updates over the TUM sequence, bytes, queries).
    #[arg(long)]
    esdf: bool,
    /// With --esdf: distances kept below this (metres).
    #[arg(long, default_value_t = 2.0)]
    esdf_max_distance: f64,
    /// With --esdf: what unknown voxels count as, free or occupied.
    #[arg(long, default_value = "free")]
    esdf_unknown: voxmap_map::field::UnknownPolicy,
    /// With --esdf: the TUM RGB-D folder (depth/*.png, my_association.txt); default
    /// shared/data/real/tum_fr2_pioneer_slam2.
    #[arg(long, value_name = "DIR")]
    esdf_sequence: Option<PathBuf>,
    /// With --esdf: also write the TUM frames (DIR/tum/*.pcd) and scan.dat
    /// (DIR/scan_dat.pcd) as PCD files here, for bench/esdf_vs_edt3d.sh.
    #[arg(long, value_name = "DIR")]
    esdf_write_pcd: Option<PathBuf>,
    /// Instead: the long-mission benchmark: a LiDAR driven around the procedural city and
    /// back, the map without a budget and under --memory-budget (each a process of its
    /// own): frame p50/p99, peak RSS, tile traffic, final maps compared.
    #[arg(long)]
    mission: bool,
    /// With --mission: frames along the route.
    #[arg(long, default_value_t = 2000)]
    mission_frames: usize,
    /// With --mission: the route goes around this many blocks (48 m) a side.
    #[arg(long, default_value_t = 8)]
    mission_blocks: u32,
    /// With --mission: the budgeted run's memory budget.
    #[arg(long, default_value = "256M")]
    memory_budget: String,
    /// With --mission: alternated rounds of the two runs.
    #[arg(long, default_value_t = 1)]
    mission_rounds: usize,
    /// With --mission: keep a distance field too (2 m, over the whole map; its bands go
    /// to the store with their tiles, and into the final map files).
    #[arg(long)]
    mission_esdf: bool,
    /// With --mission: keep the stores and maps here (default: a temporary directory,
    /// removed after).
    #[arg(long, value_name = "DIR")]
    mission_dir: Option<PathBuf>,
    /// One mission run in this process (the parent's child).
    #[arg(long, hide = true)]
    mission_child: bool,
}

/// The paper's VDB-PAR times (12 threads, ms) for (kind, points, range).
fn paper_vdb_par(name: &str) -> Option<f64> {
    Some(match name {
        "structured_50000_6m" => 10.0,
        "random_50000_6m" => 20.0,
        "structured_500000_6m" => 54.0,
        "random_500000_6m" => 74.0,
        "structured_50000_60m" => 1308.0,
        "random_50000_60m" => 5581.0,
        "structured_500000_60m" => 1979.0,
        "random_500000_60m" => 10339.0,
        _ => return None,
    })
}

/// Max range encoded in a workload name (`..._60m`).
fn range_of(name: &str) -> Option<f64> {
    name.rsplit('_').next()?.strip_suffix('m')?.parse().ok()
}

/// Find `shared/bench/gen_workloads.py` beside the checkout (or `$VOXMAP_SHARED`).
pub fn shared_dir() -> Option<PathBuf> {
    if let Ok(d) = std::env::var("VOXMAP_SHARED") {
        return Some(PathBuf::from(d));
    }
    let mut starts = vec![std::env::current_dir().ok()?];
    if let Ok(exe) = std::env::current_exe() {
        starts.push(exe);
    }
    starts.push(PathBuf::from(env!("CARGO_MANIFEST_DIR")));
    for s in starts {
        for dir in s.ancestors() {
            let c = dir.join("shared");
            if c.join("bench/gen_workloads.py").is_file() {
                return Some(c);
            }
        }
    }
    None
}

fn generated_workloads() -> Result<PathBuf> {
    let out = std::env::temp_dir().join("voxmap-workloads-seed42");
    let names = ["structured", "random"].iter().flat_map(|k| {
        ["50000_6m", "50000_60m", "500000_6m", "500000_60m"].map(|s| format!("{k}_{s}.pcd"))
    });
    if names.clone().all(|n| out.join(n).is_file()) {
        return Ok(out);
    }
    let script = shared_dir().context(
        "shared/bench/gen_workloads.py not found; pass --workloads DIR or set VOXMAP_SHARED",
    )?;
    eprintln!(
        "generating the paper's workloads into {} ...",
        out.display()
    );
    let st = std::process::Command::new("python3")
        .arg(script.join("bench/gen_workloads.py"))
        .arg(&out)
        .stdout(std::process::Stdio::null())
        .status()
        .context("running python3")?;
    if !st.success() {
        bail!("gen_workloads.py failed: {st}");
    }
    Ok(out)
}

fn list_pcd(dir: &Path) -> Result<Vec<PathBuf>> {
    let mut v: Vec<PathBuf> = std::fs::read_dir(dir)
        .with_context(|| format!("reading {}", dir.display()))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|e| e == "pcd"))
        .collect();
    // Small before large, 6 m before 60 m.
    v.sort_by_key(|p| {
        let n = p
            .file_stem()
            .unwrap_or_default()
            .to_string_lossy()
            .to_string();
        let pts: u64 = n
            .split('_')
            .nth(1)
            .and_then(|s| s.parse().ok())
            .unwrap_or(0);
        (range_of(&n).unwrap_or(0.0) as u64, pts, n)
    });
    Ok(v)
}

/// The workload files whose name (file stem) contains `filter`, with their names.
fn selected<'f>(
    files: &'f [PathBuf],
    filter: Option<&'f str>,
) -> impl Iterator<Item = (String, &'f PathBuf)> + 'f {
    files
        .iter()
        .map(|f| {
            (
                f.file_stem()
                    .unwrap_or_default()
                    .to_string_lossy()
                    .to_string(),
                f,
            )
        })
        .filter(move |(name, _)| filter.is_none_or(|s| name.contains(s)))
}

fn mode_of(name: &str, a: &BenchArgs) -> Result<RayMode> {
    Ok(match name {
        "exact" => RayMode::Exact,
        "subsample" => RayMode::Subsample {
            factor: a.subsample_factor,
        },
        "bundle" => RayMode::Bundle {
            threshold: a.bundle_threshold,
        },
        "unique_end" => RayMode::UniqueEnd,
        o => bail!("unknown mode '{o}' (exact, subsample, bundle, unique_end)"),
    })
}

fn ms(d: std::time::Duration) -> f64 {
    d.as_secs_f64() * 1e3
}

pub fn run(a: BenchArgs) -> Result<()> {
    if a.mission {
        return if a.mission_child {
            mission::child(&a)
        } else {
            mission::run(&a)
        };
    }
    if let Some(secs) = a.e2e {
        return e2e::run(secs, a.pin_threads, a.e2e_ros2, a.e2e_esdf);
    }
    let dir = match &a.workloads {
        Some(d) => d.clone(),
        None => generated_workloads()?,
    };
    let files = list_pcd(&dir)?;
    if files.is_empty() {
        bail!("no .pcd files in {}", dir.display());
    }
    if a.runs == 0 {
        bail!("--runs must be >= 1");
    }
    if a.esdf {
        return esdf::run(&a, &files);
    }
    if !a.json {
        println!(
            "voxmap bench: resolution {} m, {} timed runs per row (median, fresh map per run, after 1 warm-up), {} cores",
            a.resolution,
            a.runs,
            std::thread::available_parallelism().map_or(1, |n| n.get())
        );
        println!(
            "{:<22} {:>2} {:<10} {:<6} {:<6} {:>7} {:>10} {:>5} {:>9} {:>8} {:>8} {:>7} {:>6} | {:>6} {:>6} {:>6} {:>6} | {:>10} {:>10} {:>6} | {:>8}",
            "workload", "th", "mode", "kernel", "walk", "rays", "steps", "cov%", "median", "min", "max", "Mpt/s", "ns/st",
            "prep", "ray", "merge", "upd", "occupied", "free", "B/vox", "paper"
        );
    }
    let mut snapshots = Vec::new();
    for (name, f) in selected(&files, a.filter.as_deref()) {
        bench_workload(&a, &name, f, &mut snapshots)?;
    }
    if !a.json {
        println!("kernel = the vector kernels in use (VOXMAP_KERNEL forces one); walk = dense (per-thread bit grids over a small frame's box) or sparse; steps = voxels on the rays; cov% = of those, the share the dense walk skipped in the box around the sensor that its first rays had marked through; ns/st = median ns per step (covered or walked) per thread; B/vox = map bytes per touched voxel; paper = VDB-PAR, 12 threads, ms");
    }
    print_snapshots(&a, &snapshots);
    Ok(())
}

/// The rows of one workload: each ray mode on each thread count, into fresh maps; the
/// snapshot measurements of its exact map go to `snapshots`.
fn bench_workload(
    a: &BenchArgs,
    name: &str,
    f: &Path,
    snapshots: &mut Vec<(String, SnapshotBench)>,
) -> Result<()> {
    let name = name.to_string();
    {
        let cloud = pcd::read(f)?;
        let max_range = range_of(&name).unwrap_or(30.0);
        let mut exact_counts = None;
        // The exact map of this frame, and each mode's agreement with it (the same on any
        // thread count: computed once per mode).
        let mut exact_map: Option<OccupancyMap> = None;
        for m in &a.modes {
            let mut agreement: Option<Agreement> = None;
            let mode = mode_of(m, a)?;
            for &threads in &a.threads {
                let cfg = IntegratorConfig {
                    threads,
                    max_range,
                    mode,
                    pin_threads: a.pin_threads,
                };
                let mut mapper = Mapper::new(&MapperConfig {
                    resolution: a.resolution,
                    model: SensorModel::default(),
                    integrator: cfg,
                    field: None,
                })?;
                let frame = Frame {
                    pose: cloud.pose,
                    points: &cloud.points,
                };
                let mut times = Vec::new();
                let mut phases = Vec::new();
                let mut last = None;
                for run in 0..=a.runs {
                    // A fresh map each run; the last run's is dropped before the timing.
                    let fresh = OccupancyMap::new(a.resolution, SensorModel::default())?;
                    drop(mapper.replace_map(fresh, None)?);
                    let t = Instant::now();
                    let r = mapper.insert(&frame, FrameStamp::default())?.integrate;
                    let el = t.elapsed();
                    if run > 0 {
                        times.push(ms(el));
                        phases.push(r.times);
                    }
                    last = Some(r);
                }
                let r = last.expect("runs >= 1");
                let counts = mapper.map().counts();
                let mem = mapper.map().memory_bytes();
                let med = median(&mut times);
                if mode == RayMode::Exact && Some(&threads) == a.threads.last() && !a.no_snapshot {
                    let t = cloud.pose.translation.vector;
                    let sensor = [t.x, t.y, t.z];
                    snapshots.push((name.clone(), snapshot_bench(&mapper, med, sensor)));
                }
                let kernel = mapper.integrator().kernel().name();
                let (map, _) = mapper.into_parts();
                if mode == RayMode::Exact {
                    exact_map = Some(map);
                } else if let (Some(e), None) = (&exact_map, &agreement) {
                    agreement = Some(Agreement::of(&map, e));
                    drop(map);
                } else {
                    drop(map);
                }
                let (min, max) = (times[0], times[times.len() - 1]);
                let p = median_phases(&mut phases);
                let ns_step = med * 1e6 * threads as f64 / r.voxel_steps.max(1) as f64;
                let covered_pct = 100.0 * r.covered_steps as f64 / r.voxel_steps.max(1) as f64;
                let mpts = r.points as f64 / (med * 1e3);
                let bpv = mem as f64 / r.touched_voxels.max(1) as f64;
                if mode == RayMode::Exact {
                    exact_counts = Some(counts);
                }
                let paper = paper_vdb_par(&name);
                let walk = if r.dense { "dense" } else { "sparse" };
                if a.json {
                    let mut o = serde_json::json!({
                        "workload": name, "threads": threads, "mode": mode.name(), "kernel": kernel, "walk": walk, "runs": a.runs,
                        "median_ms": med, "min_ms": min, "max_ms": max, "points": r.points, "rays": r.rays,
                        "voxel_steps": r.voxel_steps, "covered_steps": r.covered_steps, "occupied": counts.occupied, "free": counts.free,
                        "memory_bytes": mem, "touched_voxels": r.touched_voxels, "touched_leaves": r.touched_leaves,
                        "mpoints_per_s": mpts, "ns_per_step_per_thread": ns_step, "bytes_per_touched_voxel": bpv,
                        "prepare_ms": ms(p.prepare), "select_ms": ms(p.select), "raycast_ms": ms(p.raycast), "merge_ms": ms(p.merge), "update_ms": ms(p.update),
                        "paper_vdb_par_12t_ms": paper,
                    });
                    if let (Some(e), true) = (exact_counts, mode != RayMode::Exact) {
                        o["occupied_vs_exact"] =
                            serde_json::json!(counts.occupied as f64 / e.occupied.max(1) as f64);
                        o["free_vs_exact"] =
                            serde_json::json!(counts.free as f64 / e.free.max(1) as f64);
                    }
                    if let Some(g) = &agreement {
                        o["vs_exact"] = g.json();
                    }
                    println!("{o}");
                } else {
                    println!(
                        "{:<22} {:>2} {:<10} {:<6} {:<6} {:>7} {:>10} {:>5.1} {:>9.2} {:>8.2} {:>8.2} {:>7.2} {:>6.2} | {:>6.1} {:>6.1} {:>6.1} {:>6.1} | {:>10} {:>10} {:>6.2} | {:>8}",
                        name, threads, mode.name(), kernel, walk, r.rays, r.voxel_steps, covered_pct, med, min, max, mpts, ns_step,
                        ms(p.prepare), ms(p.raycast), ms(p.merge), ms(p.update),
                        counts.occupied, counts.free, bpv, paper.map_or("-".into(), |v| format!("{v:.0}")),
                    );
                    if let Some(g) = &agreement {
                        println!("{:<22}    vs exact: {}", "", g.line());
                    }
                    if mode != RayMode::Exact {
                        println!(
                            "{:<22}    selection (choosing and dropping rays, part of prep): {:.2} ms, {:.0}% of the frame",
                            "",
                            ms(p.select),
                            100.0 * ms(p.select) / med.max(1e-9)
                        );
                    }
                }
            }
        }
    }
    Ok(())
}

/// The snapshot and map-file measurements of the exact maps.
fn print_snapshots(a: &BenchArgs, snapshots: &[(String, SnapshotBench)]) {
    if !a.json && !snapshots.is_empty() {
        println!();
        println!(
            "snapshot (exact map, mask-only form){:<4} {:>10} {:>10} {:>9} {:>9} {:>9} {:>9} {:>8} {:>8} {:>8} {:>9} {:>9} {:>9} {:>8}",
            "", "bytes", "leaves", "B/known", "B/leaf", "encode", "xfaster", "box ms", "open ms", "ms chk", "query ns", "batch ns", "los10m ns", "read ns"
        );
    }
    for (name, s) in snapshots {
        if a.json {
            println!(
                "{}",
                serde_json::json!({
                    "section": "snapshot", "workload": name, "bytes": s.bytes, "leaves": s.leaves, "known": s.known,
                    "bytes_per_known_voxel": s.bytes as f64 / s.known.max(1) as f64,
                    "bytes_per_leaf": s.bytes as f64 / s.leaves.max(1) as f64,
                    "map_memory_bytes": s.map_bytes, "encode_ms": s.encode_ms, "integrate_ms": s.integrate_ms,
                    "box_encode_ms": s.box_encode_ms, "box_bytes": s.box_bytes,
                    "open_ms": s.open_ms, "open_checked_ms": s.open_checked_ms,
                    "point_query_ns": s.query_ns, "point_query_batched_ns": s.batch_query_ns,
                    "first_hit_10m_ns": s.los_ns, "dependent_read_ns": s.read_ns,
                    "mapfile_bytes": s.file_bytes, "mapfile_encode_ms": s.file_encode_ms,
                    "mapfile_decode_ms": s.file_decode_ms,
                })
            );
        } else {
            println!(
                "{:<40} {:>10} {:>10} {:>9.3} {:>9.1} {:>9.2} {:>9.1} {:>8.2} {:>8.3} {:>8.3} {:>9.1} {:>9.1} {:>9.0} {:>8.1}",
                name, s.bytes, s.leaves, s.bytes as f64 / s.known.max(1) as f64, s.bytes as f64 / s.leaves.max(1) as f64,
                s.encode_ms, s.integrate_ms / s.encode_ms, s.box_encode_ms, s.open_ms, s.open_checked_ms, s.query_ns, s.batch_query_ns, s.los_ns,
                s.read_ns
            );
        }
    }
    if !a.json && !snapshots.is_empty() {
        println!("xfaster = integrate median / encode (median of 5); box = encode of a 20 x 20 x 6 m box around the sensor (median of 3); query = state at random known voxels (median over batches of {QUERY_BATCH} of ns per query, one state() call each); batch = the same voxels through one states() call per batch; los10m = first_hit on a 10 m segment (median ns); read = one dependent read of a random 64-byte line of a buffer the snapshot's size, timed as the queries: what a query that misses cache pays per miss on this machine");
        println!();
        println!(
            "{:<40} {:>12} {:>10} {:>10}",
            "map file (in memory, no disk)", "bytes", "encode ms", "decode ms"
        );
        for (name, s) in snapshots {
            println!(
                "{:<40} {:>12} {:>10.1} {:>10.1}",
                name, s.file_bytes, s.file_encode_ms, s.file_decode_ms
            );
        }
    }
}

/// How a ray mode's map agrees with the exact map of the same frame.
struct Agreement {
    /// Voxels known in both maps, and those of them in the same state.
    both_known: u64,
    same_state: u64,
    /// Occupied in both; occupied in the mode's map; occupied in the exact map.
    occupied_both: u64,
    occupied_mode: u64,
    occupied_exact: u64,
    /// Known in one map only.
    mode_only: u64,
    exact_only: u64,
}

impl Agreement {
    fn of(mode: &OccupancyMap, exact: &OccupancyMap) -> Self {
        let mut g = Agreement {
            both_known: 0,
            same_state: 0,
            occupied_both: 0,
            occupied_mode: 0,
            occupied_exact: exact.counts().occupied,
            mode_only: 0,
            exact_only: 0,
        };
        for (v, _) in mode.grid().active_voxels() {
            let (m, e) = (mode.state(v), exact.state(v));
            let occupied = m == VoxelState::Occupied;
            g.occupied_mode += u64::from(occupied);
            if e == VoxelState::Unknown {
                g.mode_only += 1;
                continue;
            }
            g.both_known += 1;
            g.same_state += u64::from(m == e);
            g.occupied_both += u64::from(occupied && e == VoxelState::Occupied);
        }
        let c = exact.counts();
        g.exact_only = (c.occupied + c.free).saturating_sub(g.both_known);
        g
    }

    fn ratio(a: u64, b: u64) -> f64 {
        a as f64 / b.max(1) as f64
    }

    fn line(&self) -> String {
        format!(
            "known in both {} ({:.2}% same state); occupied precision {:.4} recall {:.4}; known in this mode only {}, in exact only {}",
            self.both_known,
            100.0 * Self::ratio(self.same_state, self.both_known),
            Self::ratio(self.occupied_both, self.occupied_mode),
            Self::ratio(self.occupied_both, self.occupied_exact),
            self.mode_only,
            self.exact_only
        )
    }

    fn json(&self) -> serde_json::Value {
        serde_json::json!({
            "known_in_both": self.both_known, "same_state": self.same_state,
            "occupied_precision": Self::ratio(self.occupied_both, self.occupied_mode),
            "occupied_recall": Self::ratio(self.occupied_both, self.occupied_exact),
            "known_in_mode_only": self.mode_only, "known_in_exact_only": self.exact_only,
        })
    }
}

struct SnapshotBench {
    bytes: usize,
    leaves: u64,
    known: u64,
    map_bytes: usize,
    encode_ms: f64,
    integrate_ms: f64,
    /// A 20 x 20 x 6 m box around the sensor: encode ms (median of 3) and bytes.
    box_encode_ms: f64,
    box_bytes: usize,
    open_ms: f64,
    open_checked_ms: f64,
    query_ns: f64,
    /// The same queries through [`SnapshotView::states`], a batch per call.
    batch_query_ns: f64,
    los_ns: f64,
    /// ns per dependent read of a random line of a buffer the snapshot's size.
    read_ns: f64,
    /// Map file, in memory (no disk): bytes, encode and decode ms.
    file_bytes: usize,
    file_encode_ms: f64,
    file_decode_ms: f64,
}

/// This machine's cost of a cache miss at a snapshot's size: ns per read of a random
/// 64-byte line of a buffer `bytes` long, each read's address taken from the one before
/// (a random cycle through all lines), timed in batches like the point queries.
fn dependent_read_ns(bytes: usize, rng: &mut crate::rng::XorShift) -> f64 {
    let lines = (bytes / 64).max(2);
    let mut order: Vec<usize> = (0..lines).collect();
    rng.shuffle(&mut order);
    // Word 0 of each line holds the next line of the cycle.
    let mut next = vec![0usize; lines * 8];
    for (i, &line) in order.iter().enumerate() {
        next[line * 8] = order[(i + 1) % lines];
    }
    let mut at = order[0];
    let mut batches: Vec<f64> = (0..400)
        .map(|_| {
            let t = Instant::now();
            for _ in 0..QUERY_BATCH {
                at = next[at * 8];
            }
            t.elapsed().as_secs_f64() * 1e9 / QUERY_BATCH as f64
        })
        .collect();
    std::hint::black_box(at);
    median(&mut batches)
}

/// Point queries per timed batch.
const QUERY_BATCH: usize = 256;

/// The median of `v` (reordered); 0 when empty.
fn median(v: &mut [f64]) -> f64 {
    v.sort_by(f64::total_cmp);
    v.get(v.len() / 2).copied().unwrap_or(0.0)
}

/// Encode on the integrator's pool, as the service does, so encode and integrate use the
/// same threads.
fn snapshot_bench(mapper: &Mapper, integrate_ms: f64, sensor: [f64; 3]) -> SnapshotBench {
    use voxmap_map::snapshot::{Meta, Scope, SnapshotView};
    use voxmap_map::{VoxelCoord, WorldPoint};
    let map = mapper.map();
    let meta = Meta::default();
    let mut buf = vec![0u8; mapper.snapshot(Scope::Whole, meta).encoded_len()];
    // Touch the pages outside the timing.
    buf.iter_mut().step_by(4096).for_each(|b| *b = 1);
    // Five encodes, as the service encodes every frame: the first pays for memory the
    // later ones reuse, and the median is what a frame pays.
    let mut enc = Vec::new();
    for _ in 0..5 {
        let t = Instant::now();
        let plan = mapper.snapshot(Scope::Whole, meta);
        mapper.write_snapshot(&plan, &mut buf).expect("sized");
        enc.push(ms(t.elapsed()));
    }
    let around = Scope::Box {
        min: [sensor[0] - 10.0, sensor[1] - 10.0, sensor[2] - 3.0],
        max: [sensor[0] + 10.0, sensor[1] + 10.0, sensor[2] + 3.0],
    };
    let mut box_enc = Vec::new();
    let mut box_bytes = 0;
    for _ in 0..3 {
        let t = Instant::now();
        box_bytes = mapper.install(|| mapper.snapshot(around, meta).to_vec().len());
        box_enc.push(ms(t.elapsed()));
    }
    let t = Instant::now();
    let view = SnapshotView::open(&buf).expect("fresh snapshot opens");
    let open_ms = ms(t.elapsed());
    let t = Instant::now();
    SnapshotView::open_checked(&buf).expect("checksum");
    let open_checked_ms = ms(t.elapsed());
    // Random known voxels (a strided sample), queried in shuffled order.
    let n = map.grid().active_count().max(1);
    let stride = (n / 200_000).max(1) as usize;
    let mut pts: Vec<VoxelCoord> = map
        .grid()
        .active_voxels()
        .step_by(stride)
        .map(|(v, _)| v)
        .collect();
    let mut rng = crate::rng::XorShift::new(0x2545F4914F6CDD1D);
    rng.shuffle(&mut pts);
    // A query takes about as long as reading the clock, so queries are timed in batches:
    // the median over batches of the mean per query. `occupied` answers a batch.
    let per_query_ns = |occupied: &mut dyn FnMut(&[VoxelCoord]) -> usize| {
        let mut batches: Vec<f64> = pts
            .chunks(QUERY_BATCH)
            .map(|batch| {
                let t = Instant::now();
                std::hint::black_box(occupied(batch));
                t.elapsed().as_secs_f64() * 1e9 / batch.len() as f64
            })
            .collect();
        median(&mut batches)
    };
    let occupied = voxmap_map::VoxelState::Occupied;
    let query_ns =
        per_query_ns(&mut |batch| batch.iter().filter(|&&v| view.state(v) == occupied).count());
    let mut states = Vec::with_capacity(QUERY_BATCH);
    let batch_query_ns = per_query_ns(&mut |batch| {
        states.clear();
        view.states(batch, &mut states);
        states.iter().filter(|&&s| s == occupied).count()
    });
    // 10 m segments from near the sensor in random directions.
    let mut segs = Vec::new();
    for _ in 0..20_000 {
        let mut r = || rng.uniform() * 2.0 - 1.0;
        let d = nalgebra::Vector3::new(r(), r(), r()).normalize() * 10.0;
        let a = WorldPoint::new(r() * 0.5, r() * 0.5, r() * 0.2);
        segs.push((a, a + d));
    }
    // A walk takes a microsecond or so: each is timed on its own.
    let mut walks: Vec<f64> = segs
        .iter()
        .map(|(a, b)| {
            let t = Instant::now();
            std::hint::black_box(view.first_hit(a, b, false).ok());
            t.elapsed().as_secs_f64() * 1e9
        })
        .collect();
    let los_ns = median(&mut walks);
    let read_ns = dependent_read_ns(buf.len(), &mut rng);
    let (known, _) = view.counts();
    // The map file, encoded and decoded on the integrator's pool (the service encodes a
    // save there; it decodes a load on the file worker, with rayon's global pool).
    let t = Instant::now();
    let file = mapper.install(|| voxmap_map::io::mapfile::encode_map_parts(map));
    let file_encode_ms = ms(t.elapsed());
    let file = file.into_bytes();
    let t = Instant::now();
    let back = mapper.install(|| voxmap_map::io::mapfile::decode_map(&file));
    let file_decode_ms = ms(t.elapsed());
    assert!(
        back.is_ok_and(|m| m.grid().leaf_count() == map.grid().leaf_count()),
        "map file round trip"
    );
    SnapshotBench {
        bytes: buf.len(),
        leaves: view.leaf_count(),
        known,
        map_bytes: map.memory_bytes(),
        encode_ms: median(&mut enc),
        integrate_ms,
        box_encode_ms: median(&mut box_enc),
        box_bytes,
        open_ms,
        open_checked_ms,
        query_ns,
        batch_query_ns,
        los_ns,
        read_ns,
        file_bytes: file.len(),
        file_encode_ms,
        file_decode_ms,
    }
}

fn median_phases(p: &mut [PhaseTimes]) -> PhaseTimes {
    let pick = |f: fn(&PhaseTimes) -> std::time::Duration| {
        let mut v: Vec<_> = p.iter().map(f).collect();
        v.sort();
        v[v.len() / 2]
    };
    PhaseTimes {
        prepare: pick(|t| t.prepare),
        select: pick(|t| t.select),
        raycast: pick(|t| t.raycast),
        merge: pick(|t| t.merge),
        update: pick(|t| t.update),
    }
}

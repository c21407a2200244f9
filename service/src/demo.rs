//! `voxmap demo`: the whole system on one machine with no data. Starts `voxmap serve`, a
//! simulated LiDAR moving through a procedural indoor scene (`sim-sensor`) and a planner
//! reading snapshots in place (`sim-planner`), each its own process; prints live stats;
//! then writes `map.png`, `slice_1m.png`, `map.bt` and `map.vxm` and stops everything it
//! started.

use crate::render::{self, View};
use crate::sim;
use crate::simproc::Kids;
use anyhow::{anyhow, bail, Context, Result};
use clap::Args;
use std::path::PathBuf;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};
use voxmap_client::{MapControl, SnapshotSubscriber};
use voxmap_map::io::{mapfile, octomap};

#[derive(Args, Debug)]
pub struct DemoArgs {
    /// How long the sensor drives, seconds.
    #[arg(long, default_value_t = 20.0)]
    pub seconds: f64,
    /// Where the map, its pictures and the logs go.
    #[arg(long, default_value = "voxmap-demo")]
    pub out: PathBuf,
    /// Voxel edge, metres.
    #[arg(long, default_value_t = 0.1)]
    pub resolution: f64,
}

pub fn run(a: DemoArgs) -> Result<()> {
    if !(a.seconds.is_finite() && a.seconds > 0.0 && a.seconds <= 3600.0) {
        bail!("--seconds must be in (0, 3600]");
    }
    std::fs::create_dir_all(&a.out).with_context(|| format!("creating {}", a.out.display()))?;
    let out = std::path::absolute(&a.out)?;
    let exe = std::env::current_exe()?;
    let prefix = format!("voxmap-demo-{}", std::process::id());
    let secs = format!("{}", a.seconds);
    let mut kids = Kids(Vec::new());
    let log = std::fs::File::create(out.join("service.log"))?;
    println!(
        "voxmap demo: starting the service (prefix '{prefix}', log in {})",
        out.join("service.log").display()
    );
    kids.0.push((
        "service",
        Command::new(&exe)
            .args(["serve", "--prefix", &prefix, "--max-range", "20"])
            .args(["--resolution", &a.resolution.to_string()])
            .stdout(Stdio::null())
            .stderr(log)
            .spawn()
            .context("starting voxmap serve")?,
    ));
    let mut snapshots = SnapshotSubscriber::connect(&prefix, "default")?;
    if !snapshots.wait_for_update(Duration::from_secs(20))? {
        bail!(
            "the service published no snapshot within 20 s; see {}",
            out.join("service.log").display()
        );
    }
    let control = MapControl::connect(&prefix, "default")?;
    for role in ["sim-planner", "sim-sensor"] {
        kids.0.push((
            role,
            Command::new(&exe)
                .args([role, "--prefix", &prefix, "--seconds", &secs])
                .spawn()
                .with_context(|| format!("starting {role}"))?,
        ));
    }
    println!(
        "voxmap demo: a simulated 64-beam LiDAR drives {:.1} m through 4 rooms in {} s; a planner reads snapshots",
        sim::path_length(),
        a.seconds
    );
    let started = Instant::now();
    let mut last = (0u64, 0u64, Instant::now());
    loop {
        std::thread::sleep(Duration::from_secs(1));
        let s = control.stats()?;
        let dt = last.2.elapsed().as_secs_f64();
        println!(
            "  t {:>4.0} s | frames {:>4} ({:>4.1}/s, {} dropped) | points {:>6.2} M ({:.2} M/s) | integrate p50 {:.1} ms p99 {:.1} ms | snapshot {} KB | map {:.1} MB",
            started.elapsed().as_secs_f64(),
            s.frames_integrated,
            (s.frames_integrated - last.0) as f64 / dt,
            s.frames_dropped,
            s.points_integrated as f64 / 1e6,
            (s.points_integrated - last.1) as f64 / dt / 1e6,
            s.integrate_ms_p50,
            s.integrate_ms_p99,
            s.snapshot_bytes / 1024,
            s.map_memory_bytes as f64 / 1e6
        );
        last = (s.frames_integrated, s.points_integrated, Instant::now());
        let sensor_done = kids
            .get("sim-sensor")
            .map_or(Ok(None), |c| c.try_wait())?
            .is_some();
        if sensor_done || started.elapsed().as_secs_f64() > a.seconds + 30.0 {
            break;
        }
    }
    for role in ["sim-sensor", "sim-planner"] {
        let st = kids
            .get(role)
            .ok_or_else(|| anyhow!("{role} missing"))?
            .wait()?;
        if !st.success() {
            bail!("{role} failed: {st}");
        }
    }
    let map_path = out.join("map.vxm");
    control.save(&map_path.to_string_lossy())?;
    // SIGTERM: the service finishes its frame, publishes a last snapshot and exits 0.
    let service = kids
        .get("service")
        .ok_or_else(|| anyhow!("service missing"))?;
    // SAFETY: kill(2) with a child's pid and SIGTERM only sends a signal; no memory is
    // involved. The child is not yet reaped, so its pid cannot have been reused.
    let rc = unsafe { libc::kill(service.id() as libc::pid_t, libc::SIGTERM) };
    if rc != 0 {
        bail!(
            "could not signal the service: {}",
            std::io::Error::last_os_error()
        );
    }
    let st = service.wait()?;
    if !st.success() {
        bail!(
            "the service exited with {st}; see {}",
            out.join("service.log").display()
        );
    }
    drop(snapshots);

    let loaded = crate::files::Loaded::read(&map_path)?;
    let top = out.join("map.png");
    render::render(
        &loaded.leaves,
        loaded.resolution,
        View::Top(Some((0.1, 2.4))),
        1000,
    )?
    .write_png(&top)?;
    let slice = out.join("slice_1m.png");
    render::render(&loaded.leaves, loaded.resolution, View::Slice(1.0), 1000)?.write_png(&slice)?;
    let bt = out.join("map.bt");
    let bytes = octomap::encode_bt(loaded.leaves.iter().copied(), loaded.resolution)?;
    mapfile::write_atomic(&bt, &bytes)?;
    println!("voxmap demo: done; everything it started has stopped.");
    for (k, v) in &loaded.details {
        if matches!(*k, "occupied voxels" | "free voxels" | "bounds (known)") {
            println!("  {k:<16} {v}");
        }
    }
    println!("  map file         {}", map_path.display());
    println!("  top-down picture {}", top.display());
    println!("  slice at 1 m     {}", slice.display());
    println!("  OctoMap .bt      {} (open it with octovis)", bt.display());
    Ok(())
}

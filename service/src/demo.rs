//! `voxmap demo`: the whole system on one machine with no data. Starts `voxmap serve`, a
//! simulated LiDAR moving through a procedural indoor scene (`sim-sensor`) and a planner
//! reading snapshots in place (`sim-planner`), each its own process; prints live stats;
//! then writes a PNG and a `.bt` of the map and stops everything it started.

use crate::os::now_ns;
use crate::render::{self, View};
use crate::rng::XorShift;
use crate::sim::{self, Lidar, Scene};
use anyhow::{anyhow, bail, Context, Result};
use clap::Args;
use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};
use voxmap_client::{FramePublisher, MapControl, SnapshotSubscriber};
use voxmap_core::io::{mapfile, octomap};
use voxmap_core::{VoxelState, WorldPoint};

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

#[derive(Args, Debug)]
pub struct SimArgs {
    #[arg(long)]
    pub prefix: String,
    #[arg(long, default_value = "default")]
    pub map: String,
    #[arg(long, default_value_t = 20.0)]
    pub seconds: f64,
    /// Scans per second.
    #[arg(long, default_value_t = 10.0)]
    pub rate: f64,
    /// Planner: print one JSON line of latencies (for `bench --e2e`).
    #[arg(long)]
    pub json: bool,
    /// Run under SCHED_FIFO at this priority (0 = off).
    #[arg(long, default_value_t = 0)]
    pub rt_priority: i32,
}

/// Sensor height above the floor, metres.
const SENSOR_HEIGHT: f64 = 0.8;

/// Children killed on drop unless already reaped: whatever happens, the demo leaves no
/// process behind.
struct Kids(Vec<(&'static str, Child)>);

impl Drop for Kids {
    fn drop(&mut self) {
        for (_, c) in &mut self.0 {
            let _ = c.kill();
            let _ = c.wait();
        }
    }
}

impl Kids {
    fn get(&mut self, name: &str) -> Option<&mut Child> {
        self.0.iter_mut().find(|(n, _)| *n == name).map(|(_, c)| c)
    }
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

/// The simulated sensor: scans at `rate` Hz while moving along the path at the speed
/// that covers it in `seconds`.
pub fn sensor(a: SimArgs) -> Result<()> {
    let scene = Scene::indoor();
    let lidar = Lidar::os0_64();
    let mut publisher = FramePublisher::connect(&a.prefix, &a.map)?;
    let mut rng = XorShift::new(42);
    let speed = sim::path_length() / a.seconds;
    let mut pts = Vec::with_capacity(lidar.beams * lidar.columns);
    let started = Instant::now();
    let (mut frames, mut points) = (0u64, 0u64);
    loop {
        let due = started + Duration::from_secs_f64(frames as f64 / a.rate);
        std::thread::sleep(due.saturating_duration_since(Instant::now()));
        let t = started.elapsed().as_secs_f64();
        if t > a.seconds {
            break;
        }
        let pose = sim::pose_along(speed * t, SENSOR_HEIGHT);
        lidar.scan(&scene, &pose, &mut rng, &mut pts);
        // The scan's length is known only after casting, so it is built in a buffer and
        // copied into the loan; stamped after the copy, as a driver stamps at send time.
        let mut loan = publisher.loan(pts.len())?;
        loan.points_mut().copy_from_slice(&pts);
        loan.send(&pose, now_ns())?;
        frames += 1;
        points += pts.len() as u64;
    }
    println!("  sensor: sent {frames} scans, {points} points");
    Ok(())
}

/// The simulated planner: on each snapshot, checks in place whether the path ahead is in
/// line of sight and whether a robot-sized box along it is free.
pub fn planner(a: SimArgs) -> Result<()> {
    if a.rt_priority > 0 {
        crate::os::set_realtime(a.rt_priority)?;
    }
    let mut sub = SnapshotSubscriber::connect(&a.prefix, &a.map)?;
    let started = Instant::now();
    let mut latencies_ms = Vec::new();
    let mut handover_us = Vec::new();
    let (mut los, mut blocked, mut boxes, mut free_boxes, mut in_place) =
        (0u64, 0u64, 0u64, 0u64, true);
    let mut query_ns = 0.0;
    let mut last_seq = 0;
    let len = sim::path_length();
    while started.elapsed().as_secs_f64() < a.seconds + 1.0 {
        if !sub.wait_for_update(Duration::from_millis(100))? {
            continue;
        }
        let received = now_ns();
        let shm = sub.sample_bytes().map(|b| b.as_ptr());
        let published = sub.wire_header().map_or(0, |h| h.published_ns);
        let Some(view) = sub.latest()? else { continue };
        if view.sequence() == last_seq {
            continue;
        }
        last_seq = view.sequence();
        latencies_ms.push(received.saturating_sub(view.timestamp_ns()) as f64 / 1e6);
        handover_us.push(received.saturating_sub(published) as f64 / 1e3);
        in_place &= shm == Some(view.as_bytes().as_ptr());
        let t = Instant::now();
        let mut n = 0u64;
        // Along the path: line of sight between consecutive path points 0.5 m apart,
        // and a 0.5 x 0.5 x 1.2 m robot box at each.
        let mut s = 0.0;
        while s + 0.5 <= len {
            let p = sim::pose_along(s, SENSOR_HEIGHT).translation.vector;
            let q = sim::pose_along(s + 0.5, SENSOR_HEIGHT).translation.vector;
            let (p, q) = (WorldPoint::from(p), WorldPoint::from(q));
            los += 1;
            if !matches!(view.first_hit(&p, &q, false), Ok(None)) {
                blocked += 1;
            }
            boxes += 1;
            let lo = WorldPoint::new(p.x - 0.25, p.y - 0.25, 0.2);
            let hi = WorldPoint::new(p.x + 0.25, p.y + 0.25, 1.4);
            if view.is_box_free(&lo, &hi, false) && view.state_at(&p) == VoxelState::Free {
                free_boxes += 1;
            }
            n += 2;
            s += 0.5;
        }
        query_ns += t.elapsed().as_secs_f64() * 1e9 / n.max(1) as f64;
    }
    let snaps = latencies_ms.len();
    latencies_ms.sort_by(f64::total_cmp);
    handover_us.sort_by(f64::total_cmp);
    use crate::quantile::percentile;
    let pct = |p: f64| percentile(&latencies_ms, p);
    if a.json {
        println!(
            "{}",
            serde_json::json!({
                "snapshots": snaps,
                "in_place": in_place,
                "latency_ms_p50": pct(0.5),
                "latency_ms_p99": pct(0.99),
                "handover_us_p50": percentile(&handover_us, 0.5),
                "handover_us_p99": percentile(&handover_us, 0.99),
            })
        );
        return Ok(());
    }
    println!(
        "  planner: {snaps} snapshots read in place in shared memory: {}; frame sent -> snapshot readable p50 {:.1} ms, p99 {:.1} ms",
        if in_place { "yes" } else { "NO" },
        pct(0.5),
        pct(0.99)
    );
    println!(
        "  planner: {los} line-of-sight checks ({blocked} blocked), {boxes} robot-box checks ({free_boxes} known free), {:.0} ns per query",
        query_ns / snaps.max(1) as f64
    );
    if !in_place {
        bail!("a snapshot view did not point into the shared-memory sample");
    }
    Ok(())
}

/// `voxmap bench --e2e`: service, sensor and planner as separate processes; 65,536-point
/// scans at 0.1 m and 30 m max range. For normal and for real-time (SCHED_FIFO 10)
/// scheduling of the service's I/O thread and the planner: latency at 10 Hz; then, at
/// normal priority, the sustained rate with the sensor flat out, and the idle CPU.
pub fn e2e(seconds: f64, pin_threads: bool) -> Result<()> {
    println!("e2e: 65,536-point scans (OS0-64-like), 0.1 m, 30 m max range, service on 2 threads (pinned: {pin_threads}), sensor and planner as processes, {seconds} s per phase");
    for rt in [0, 10] {
        e2e_run(seconds, rt, pin_threads)?;
    }
    Ok(())
}

fn e2e_run(seconds: f64, rt: i32, pin_threads: bool) -> Result<()> {
    let exe = std::env::current_exe()?;
    let prefix = format!("voxmap-e2e-{}-{rt}", std::process::id());
    let (secs, rts) = (seconds.to_string(), rt.to_string());
    let mut kids = Kids(Vec::new());
    kids.0.push((
        "service",
        Command::new(&exe)
            .args([
                "serve",
                "--prefix",
                &prefix,
                "--resolution",
                "0.1",
                "--max-range",
                "30",
            ])
            .args(["--threads", "2", "--rt-priority", &rts])
            .args(["--pin-threads", &pin_threads.to_string()])
            .stdout(Stdio::null())
            .stderr(Stdio::piped())
            .spawn()?,
    ));
    let mut snapshots = SnapshotSubscriber::connect(&prefix, "default")?;
    if !snapshots.wait_for_update(Duration::from_secs(20))? {
        let mut err = String::new();
        if let Some(c) = kids.get("service") {
            if let Ok(Some(_)) = c.try_wait() {
                use std::io::Read;
                c.stderr.take().map(|mut e| e.read_to_string(&mut err));
            }
        }
        bail!("the service published no snapshot within 20 s: {err}");
    }
    drop(snapshots);
    let control = MapControl::connect(&prefix, "default")?;
    let sim = |role: &str, rate: &str, json: bool| -> Result<Child> {
        let mut c = Command::new(&exe);
        c.args([
            role,
            "--prefix",
            &prefix,
            "--seconds",
            &secs,
            "--rate",
            rate,
        ]);
        if json {
            c.args(["--json", "--rt-priority", &rts])
                .stdout(Stdio::piped());
        } else {
            c.stdout(Stdio::null());
        }
        Ok(c.spawn()?)
    };
    let planner = sim("sim-planner", "10", true)?;
    let mut sensor = sim("sim-sensor", "10", false)?;
    sensor.wait()?;
    let out = planner.wait_with_output()?;
    let p: serde_json::Value = serde_json::from_slice(&out.stdout).with_context(|| {
        format!(
            "planner report ({}): {:?}",
            out.status,
            String::from_utf8_lossy(&out.stdout)
        )
    })?;
    let s1 = control.stats()?;
    let f = |k: &str| p[k].as_f64().unwrap_or(f64::NAN);
    let sched = if rt > 0 {
        format!("SCHED_FIFO {rt}")
    } else {
        "normal".to_string()
    };
    println!(
        "  10 Hz, {sched} scheduling: {} snapshots, read in place: {}",
        p["snapshots"], p["in_place"]
    );
    println!(
        "    frame sent -> snapshot readable in planner: p50 {:.2} ms, p99 {:.2} ms",
        f("latency_ms_p50"),
        f("latency_ms_p99")
    );
    println!(
        "    of which integration p50 {:.2} ms p99 {:.2} ms, last encode {:.2} ms",
        s1.integrate_ms_p50, s1.integrate_ms_p99, s1.encode_ms_last
    );
    println!(
        "    IPC: frame send -> service receive p50 {:.1} us, p99 {:.1} us",
        s1.intake_us_p50, s1.intake_us_p99
    );
    println!(
        "    IPC: snapshot send -> planner receive p50 {:.1} us, p99 {:.1} us",
        f("handover_us_p50"),
        f("handover_us_p99")
    );
    println!(
        "    IPC share, p99 sum: {:.1} us (target 100 us)",
        s1.intake_us_p99 + f("handover_us_p99")
    );
    println!(
        "    snapshot {} bytes, map {} bytes",
        s1.snapshot_bytes, s1.map_memory_bytes
    );
    if rt == 0 {
        let t = Instant::now();
        let mut sensor = sim("sim-sensor", "1000", false)?;
        sensor.wait()?;
        let dt = t.elapsed().as_secs_f64();
        let s2 = control.stats()?;
        println!(
            "  flat out: {:.1} frames/s, {:.2} Mpoints/s integrated ({} dropped)",
            (s2.frames_integrated - s1.frames_integrated) as f64 / dt,
            (s2.points_integrated - s1.points_integrated) as f64 / dt / 1e6,
            s2.frames_dropped - s1.frames_dropped
        );
        let pid = kids
            .get("service")
            .ok_or_else(|| anyhow!("service missing"))?
            .id();
        let ticks = || -> Result<u64> {
            let st = std::fs::read_to_string(format!("/proc/{pid}/stat"))?;
            // utime and stime: fields 14 and 15 of stat, 11 and 12 (0-based) after the
            // command. Fields are taken by position: some (state, tpgid = -1) are not u64.
            let f: Vec<&str> = st
                .rsplit_once(')')
                .map_or("", |x| x.1)
                .split_whitespace()
                .collect();
            let field = |i: usize| f.get(i).and_then(|v| v.parse::<u64>().ok()).unwrap_or(0);
            Ok(field(11) + field(12))
        };
        let t0 = ticks()?;
        std::thread::sleep(Duration::from_secs(5));
        println!(
            "  idle: the service used {} CPU ticks (1/100 s) in 5 s",
            ticks()? - t0
        );
    }
    let service = kids
        .get("service")
        .ok_or_else(|| anyhow!("service missing"))?;
    // SAFETY: as in `run`: a signal to our own unreaped child.
    unsafe { libc::kill(service.id() as libc::pid_t, libc::SIGTERM) };
    service.wait()?;
    Ok(())
}

//! `voxmap bench --e2e`: the end-to-end benchmark, service, simulated sensor and planner
//! as separate processes.

use crate::simproc::Kids;
use anyhow::{anyhow, bail, Context, Result};
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::{Duration, Instant};
use voxmap_client::{MapControl, SnapshotSubscriber};

/// `voxmap bench --e2e`: service, sensor and planner as separate processes; 65,536-point
/// scans at 0.1 m and 30 m max range. For normal and for real-time (SCHED_FIFO 10)
/// scheduling of the service's I/O thread and the planner: latency at 10 Hz; then, at
/// normal priority, the sustained rate with the sensor flat out, and the idle CPU.
/// With `ros2`, instead: normal scheduling only, the service without and with `--ros2`
/// (its map topics encoded and published every 500 ms), alternated twice.
/// With `esdf`, instead: normal scheduling only, the service without and with `--esdf`
/// (the distance field updated after each frame and carried in each snapshot), alternated
/// twice: the latency from a frame to a readable field.
pub fn run(seconds: f64, pin_threads: bool, ros2: bool, esdf: bool) -> Result<()> {
    println!("e2e: 65,536-point scans (OS0-64-like), 0.1 m, 30 m max range, service on 2 threads (pinned: {pin_threads}), sensor and planner as processes, {seconds} s per phase");
    if ros2 {
        for with in [false, true, false, true] {
            println!(
                "  service {}",
                if with {
                    "with --ros2"
                } else {
                    "without --ros2"
                }
            );
            e2e_run(seconds, 0, pin_threads, with, false)?;
        }
        return Ok(());
    }
    if esdf {
        for with in [false, true, false, true] {
            println!(
                "  service {}",
                if with {
                    "with --esdf"
                } else {
                    "without --esdf"
                }
            );
            e2e_run(seconds, 0, pin_threads, false, with)?;
        }
        return Ok(());
    }
    for rt in [0, 10] {
        e2e_run(seconds, rt, pin_threads, false, false)?;
    }
    Ok(())
}

/// One phase: the service started, a sensor at 10 Hz against a planner, the latencies
/// printed; at normal priority also the flat-out rate and the idle CPU.
fn e2e_run(seconds: f64, rt: i32, pin_threads: bool, ros2: bool, esdf: bool) -> Result<()> {
    let exe = std::env::current_exe()?;
    let prefix = format!("voxmap-e2e-{}-{rt}", std::process::id());
    let (secs, rts) = (seconds.to_string(), rt.to_string());
    let mut kids = start_service(&exe, &prefix, &rts, pin_threads, ros2, esdf)?;
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
    let reader = ros2.then(ros2_reader);
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
    print_latencies(rt, &p, &s1);
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
        let t0 = cpu_ticks(pid)?;
        std::thread::sleep(Duration::from_secs(5));
        println!(
            "  idle: the service used {} CPU ticks (1/100 s) in 5 s",
            cpu_ticks(pid)? - t0
        );
    }
    if let Some((stop, t)) = reader {
        stop.store(true, Ordering::Relaxed);
        let (messages, bytes) = t
            .join()
            .map_err(|_| anyhow!("the ROS 2 reader panicked"))??;
        println!("  ROS 2 reader of the map topics: {messages} messages, {bytes} bytes of data");
    }
    let service = kids
        .get("service")
        .ok_or_else(|| anyhow!("service missing"))?;
    // SAFETY: as in `run`: a signal to our own unreaped child.
    unsafe { libc::kill(service.id() as libc::pid_t, libc::SIGTERM) };
    service.wait()?;
    Ok(())
}

/// The service as a child process, returned once its first snapshot is readable.
fn start_service(
    exe: &Path,
    prefix: &str,
    rts: &str,
    pin_threads: bool,
    ros2: bool,
    esdf: bool,
) -> Result<Kids> {
    let mut kids = Kids(Vec::new());
    kids.0.push((
        "service",
        Command::new(exe)
            .args([
                "serve",
                "--prefix",
                prefix,
                "--resolution",
                "0.1",
                "--max-range",
                "30",
            ])
            .args(["--threads", "2", "--rt-priority", rts])
            .args(["--pin-threads", &pin_threads.to_string()])
            .args(if ros2 { &["--ros2"][..] } else { &[] })
            .args(if esdf { &["--esdf"][..] } else { &[] })
            // Discovery kept to this host: the benchmark needs no peer.
            .env("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
            .stdout(Stdio::null())
            .stderr(Stdio::piped())
            .spawn()?,
    ));
    let mut snapshots = SnapshotSubscriber::connect(prefix, "default")?;
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
    Ok(kids)
}

type ReaderThread = (Arc<AtomicBool>, JoinHandle<Result<(u64, u64)>>);

/// A DDS reader of the map topics, as a remote RViz would be, until told to stop; it
/// returns the messages and bytes it took.
fn ros2_reader() -> ReaderThread {
    let stop = Arc::new(AtomicBool::new(false));
    let s = stop.clone();
    let t = std::thread::spawn(move || -> Result<(u64, u64)> {
        let d = voxmap_ros2::discovery::Discovery::from_vars(|k| {
            (k == "ROS_AUTOMATIC_DISCOVERY_RANGE").then(|| "LOCALHOST".to_string())
        })
        .map_err(|e| anyhow!(e))?;
        let mut r = voxmap_ros2::MapTopicsReader::new(&d)?;
        while !s.load(Ordering::Relaxed) {
            r.take();
            std::thread::sleep(Duration::from_millis(20));
        }
        Ok((r.messages, r.bytes))
    });
    (stop, t)
}

/// The planner's report and the service's stats at 10 Hz, for a person.
fn print_latencies(rt: i32, p: &serde_json::Value, s1: &voxmap_client::StatsWire) {
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
}

/// A process's user and system CPU time in ticks (1/100 s), from /proc.
fn cpu_ticks(pid: u32) -> Result<u64> {
    let st = std::fs::read_to_string(format!("/proc/{pid}/stat"))?;
    // utime and stime: fields 14 and 15 of stat, 11 and 12 (0-based) after the command.
    // Fields are taken by position: some (state, tpgid = -1) are not u64.
    let f: Vec<&str> = st
        .rsplit_once(')')
        .map_or("", |x| x.1)
        .split_whitespace()
        .collect();
    let field = |i: usize| f.get(i).and_then(|v| v.parse::<u64>().ok()).unwrap_or(0);
    Ok(field(11) + field(12))
}

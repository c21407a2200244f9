//! A soak: the service under the demo's sensor load (65,536 points at 10 Hz, the map
//! scoped around the sensor) with planners attached, a slow one and a stopped one, and a
//! control client asking for stats. Resident memory, open descriptors and integration
//! p99 are sampled; after the warm-up none may grow.
//!
//! Ignored by default (30 minutes); `VOXMAP_SOAK_SECONDS` sets the length:
//! `VOXMAP_SOAK_SECONDS=1800 cargo test --release -p voxmap-tests --test soak -- --ignored --nocapture`

use std::process::{Command, Stdio};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};
use voxmap_client::{MapControl, MapScope, SnapshotSubscriber};
use voxmap_tests::{connect_with_retry, unique_prefix, voxmap_bin, Service};

/// One lap of the demo's path takes the simulated sensor this long; it drives laps until
/// the end, so that after the first the map stops growing.
const LAP_SECONDS: u32 = 60;

/// A sample of the service's resources.
#[derive(Debug, Clone, Copy)]
struct Sample {
    at_s: f64,
    rss_kb: u64,
    fds: usize,
    p99_ms: f64,
    integrated: u64,
    dropped: u64,
}

fn rss_kb(pid: u32) -> u64 {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).unwrap_or_default();
    status
        .lines()
        .find_map(|l| l.strip_prefix("VmRSS:"))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse().ok())
        .unwrap_or(0)
}

fn fds(pid: u32) -> usize {
    std::fs::read_dir(format!("/proc/{pid}/fd")).map_or(0, |d| d.count())
}

#[test]
#[ignore = "30 minutes; VOXMAP_SOAK_SECONDS sets the length"]
fn soak_memory_descriptors_and_latency_stay_flat() {
    let seconds: u64 = std::env::var("VOXMAP_SOAK_SECONDS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(1800);
    // The warm-up: two laps or a sixth of the run, whichever is longer.
    let warm_up = (2 * u64::from(LAP_SECONDS)).max(seconds / 6) as f64;
    assert!(seconds as f64 > warm_up + 60.0, "too short to compare");
    let prefix = unique_prefix("soak");
    let svc = Service::spawn(&prefix, &["--threads", "2"], &[]);
    let pid = svc.child.id();
    let mut control = connect_with_retry(|| MapControl::connect(&prefix, "default"));
    control.set_timeout(Duration::from_secs(5));
    connect_with_retry(|| control.stats());
    control
        .set_scope(MapScope::AroundSensor {
            half_extents: [6.0, 6.0, 2.0],
        })
        .unwrap();
    let stop = Arc::new(AtomicBool::new(false));
    let started = Instant::now();

    // The sensor: one `voxmap sim-sensor` process per lap.
    let sensor = {
        let (p, stop) = (prefix.clone(), stop.clone());
        std::thread::spawn(move || {
            let mut laps = 0;
            while !stop.load(Ordering::Relaxed) {
                let st = Command::new(voxmap_bin())
                    .args(["sim-sensor", "--prefix", &p, "--rate", "10", "--seconds"])
                    .arg(LAP_SECONDS.to_string())
                    .stdout(Stdio::null())
                    .status()
                    .expect("sim-sensor");
                assert!(st.success(), "sim-sensor failed: {st:?}");
                laps += 1;
            }
            laps
        })
    };
    // A planner reading every snapshot (the demo's), for the whole run.
    let planner = Command::new(voxmap_bin())
        .args(["sim-planner", "--prefix", &prefix, "--seconds"])
        .arg(seconds.to_string())
        .stdout(Stdio::piped())
        .spawn()
        .expect("sim-planner");
    // A slow planner: holds each snapshot it takes for 5 s, until it takes the next, so
    // that every receive happens while it holds an older one: as much as a planner may
    // hold (two samples, qos::SNAPSHOT_BORROWED, one of them for the receive).
    let slow = {
        let (p, stop) = (prefix.clone(), stop.clone());
        std::thread::spawn(move || {
            let mut sub = connect_with_retry(|| SnapshotSubscriber::connect(&p, "default"));
            let mut held = std::collections::VecDeque::new();
            let mut taken = 0u64;
            while !stop.load(Ordering::Relaxed) {
                if let Some(h) = sub.latest_held().expect("slow planner") {
                    taken += 1;
                    held.push_back(h);
                    if held.len() > 1 {
                        held.pop_front();
                    }
                }
                std::thread::sleep(Duration::from_secs(5));
            }
            taken
        })
    };
    // A planner that stopped reading: connected, one snapshot taken, never polled again.
    let mut stopped = connect_with_retry(|| SnapshotSubscriber::connect(&prefix, "default"));
    let _ = stopped.wait_for_update(Duration::from_secs(5)).unwrap();
    let _kept = stopped.latest_held().unwrap();

    let mut samples: Vec<Sample> = Vec::new();
    while started.elapsed().as_secs() < seconds {
        std::thread::sleep(Duration::from_secs(5));
        let s = control.stats().expect("stats during the soak");
        let sample = Sample {
            at_s: started.elapsed().as_secs_f64(),
            rss_kb: rss_kb(pid),
            fds: fds(pid),
            p99_ms: s.integrate_ms_p99,
            integrated: s.frames_integrated,
            dropped: s.frames_dropped,
        };
        if samples.len().is_multiple_of(12) {
            eprintln!("soak: {sample:?}");
        }
        samples.push(sample);
    }
    stop.store(true, Ordering::Relaxed);
    let laps = sensor.join().unwrap();
    let taken = slow.join().unwrap();
    let out = planner.wait_with_output().unwrap();
    assert!(out.status.success());
    let (st, log) = svc.signal_and_wait("TERM");
    assert!(st.success(), "{log}");

    // The last minute of the warm-up against the last minute of the run.
    let end = samples.last().unwrap().at_s;
    let window = |from: f64, to: f64| -> Vec<Sample> {
        samples
            .iter()
            .filter(|s| s.at_s > from && s.at_s <= to)
            .copied()
            .collect()
    };
    let (warm, last) = (window(warm_up - 60.0, warm_up), window(end - 60.0, end));
    let max_rss = |w: &[Sample]| w.iter().map(|s| s.rss_kb).max().unwrap();
    let max_fds = |w: &[Sample]| w.iter().map(|s| s.fds).max().unwrap();
    let p99 = |w: &[Sample]| w.iter().map(|s| s.p99_ms).fold(0.0, f64::max);
    let growth = max_rss(&last) as f64 / max_rss(&warm) as f64 - 1.0;
    let first = samples.first().unwrap();
    let final_ = samples.last().unwrap();
    eprintln!(
        "soak: {seconds} s, {laps} laps, {} frames integrated ({} dropped); resident {} -> {} kB after the warm-up ({:+.2}%), peak {} kB; fds {} -> {}; integrate p99 {:.1} -> {:.1} ms; slow planner took {taken} snapshots; planner: {}",
        final_.integrated,
        final_.dropped,
        max_rss(&warm),
        max_rss(&last),
        growth * 100.0,
        samples.iter().map(|s| s.rss_kb).max().unwrap(),
        max_fds(&warm),
        max_fds(&last),
        p99(&warm),
        p99(&last),
        String::from_utf8_lossy(&out.stdout).trim()
    );
    assert!(first.integrated < final_.integrated);
    assert!(
        growth <= 0.02,
        "resident memory grew {:.2}%",
        growth * 100.0
    );
    assert!(max_fds(&last) <= max_fds(&warm), "descriptors grew");
    assert!(
        p99(&last) <= 1.5 * p99(&warm) + 1.0,
        "integration p99 drifted: {:.1} -> {:.1} ms",
        p99(&warm),
        p99(&last)
    );
}

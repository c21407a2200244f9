//! The simulated sensor and planner processes (`voxmap sim-sensor`, `voxmap sim-planner`)
//! that `demo` and `bench --e2e` start beside `voxmap serve`, and [`Kids`], which stops
//! whatever they started.

use crate::os::now_ns;
use crate::rng::XorShift;
use crate::sim::{self, Lidar, Scene};
use anyhow::{bail, Result};
use clap::Args;
use std::process::Child;
use std::time::{Duration, Instant};
use voxmap_client::{FramePublisher, SnapshotSubscriber};
use voxmap_map::{VoxelState, WorldPoint};

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
pub(crate) struct Kids(pub Vec<(&'static str, Child)>);

impl Drop for Kids {
    fn drop(&mut self) {
        for (_, c) in &mut self.0 {
            let _ = c.kill();
            let _ = c.wait();
        }
    }
}

impl Kids {
    pub fn get(&mut self, name: &str) -> Option<&mut Child> {
        self.0.iter_mut().find(|(n, _)| *n == name).map(|(_, c)| c)
    }
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
            if view.is_box_free(&lo, &hi, false) == Ok(true)
                && view.state_at(&p) == VoxelState::Free
            {
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

//! `voxmap serve`: the mapping daemon. Frames in over iceoryx2, integrated on a thread
//! pool, snapshots out, encoded straight into loaned shared-memory samples.

use crate::config::MappingArgs;
use crate::filejobs::{Done, FileWorker, Job};
use crate::os::now_ns;
use anyhow::{anyhow, Context, Result};
use clap::Args;
use iceoryx2::port::update_connections::UpdateConnections;
use iceoryx2::prelude::*;
use iceoryx2::waitset::WaitSetRunResult;
use std::path::PathBuf;
use std::time::{Duration, Instant};
use voxmap_client::{open_control, open_event, open_frames, open_snapshots, qos};
use voxmap_core::io::mapfile;
use voxmap_core::snapshot::{Meta, Plan, Scope};
use voxmap_core::wire::{
    ControlKind, ControlRequest, ControlResponse, ServiceNames, SnapshotHeader, StatsWire,
    SNAPSHOT_WIRE_VERSION,
};
use voxmap_core::{Frame, Integrator, OccupancyMap};

#[derive(Args, Debug, Clone)]
pub struct ServeArgs {
    #[command(flatten)]
    pub mapping: MappingArgs,
    /// Service-name prefix: isolates one deployment (or test) from another.
    #[arg(long)]
    pub prefix: Option<String>,
    /// Map name under the prefix.
    #[arg(long)]
    pub map: Option<String>,
    /// Resume from this map file (its resolution and sensor model replace the configured).
    #[arg(long)]
    pub load: Option<PathBuf>,
    /// Save the map here on SIGINT/SIGTERM.
    #[arg(long)]
    pub save_on_exit: Option<PathBuf>,
    /// Include per-voxel log-odds in snapshots (512 bytes per leaf).
    #[arg(long)]
    pub snapshot_values: bool,
    /// Publish at most one snapshot per this many milliseconds (0 = after every frame).
    #[arg(long)]
    pub snapshot_interval_ms: Option<f64>,
    /// Frames arriving faster than they integrate: latest or queue.
    #[arg(long)]
    pub intake: Option<String>,
    /// Frames kept waiting under --intake queue (1..=4).
    #[arg(long)]
    pub queue_depth: Option<usize>,
    /// Run the frame/snapshot thread under SCHED_FIFO at this priority (1..=99; 0 = off).
    #[arg(long)]
    pub rt_priority: Option<i32>,
    /// Exit after this many seconds (for demos and tests); 0 = run until a signal.
    #[arg(long, default_value_t = 0.0)]
    pub exit_after: f64,
}

impl ServeArgs {
    /// The configuration with this command's own flags applied.
    pub fn resolve(&self) -> Result<crate::config::Config> {
        let mut c = self.mapping.resolve()?;
        if let Some(p) = &self.prefix {
            c.prefix = p.clone();
        }
        if let Some(m) = &self.map {
            c.map = m.clone();
        }
        c.snapshot_values |= self.snapshot_values;
        if let Some(v) = self.snapshot_interval_ms {
            c.snapshot_interval_ms = v;
        }
        if let Some(v) = &self.intake {
            c.intake = v.clone();
        }
        if let Some(v) = self.queue_depth {
            c.queue_depth = v;
        }
        if let Some(v) = self.rt_priority {
            c.rt_priority = v;
        }
        c.check()?;
        Ok(c)
    }
}

/// Counters for the periodic log line and the `stats` request.
#[derive(Default, Debug)]
struct Stats {
    received: u64,
    integrated: u64,
    dropped: u64,
    rejected: u64,
    points: u64,
    skipped_points: u64,
    /// Integration times (ms) of the last frames, oldest first.
    integrate_ms: std::collections::VecDeque<f64>,
    /// Send-to-receive times (us) of the last time-stamped frames.
    intake_us: std::collections::VecDeque<f64>,
    last_snapshot_bytes: usize,
    last_encode_ms: f64,
    sequence: u64,
    publish_failures: u64,
}

impl Stats {
    fn record(window: &mut std::collections::VecDeque<f64>, x: f64) {
        if window.len() == 1024 {
            window.pop_front();
        }
        window.push_back(x);
    }

    fn wire(&self, map: &OccupancyMap) -> StatsWire {
        let sorted = |w: &std::collections::VecDeque<f64>| {
            let mut t: Vec<f64> = w.iter().copied().collect();
            t.sort_by(f64::total_cmp);
            t
        };
        let (t, intake) = (sorted(&self.integrate_ms), sorted(&self.intake_us));
        StatsWire {
            frames_received: self.received,
            frames_integrated: self.integrated,
            frames_dropped: self.dropped,
            frames_rejected: self.rejected,
            points_integrated: self.points,
            points_skipped: self.skipped_points,
            map_leaves: map.grid().leaf_count() as u64,
            map_memory_bytes: map.memory_bytes() as u64,
            snapshot_bytes: self.last_snapshot_bytes as u64,
            snapshot_sequence: self.sequence,
            integrate_ms_p50: percentile(&t, 0.5),
            integrate_ms_p99: percentile(&t, 0.99),
            integrate_ms_max: t.last().copied().unwrap_or(0.0),
            encode_ms_last: self.last_encode_ms,
            intake_us_p50: percentile(&intake, 0.5),
            intake_us_p99: percentile(&intake, 0.99),
        }
    }

    fn log_line(&self, map: &OccupancyMap) -> String {
        let w = self.wire(map);
        format!(
            "frames received {} integrated {} dropped {} rejected {}; points {} (skipped {}); integrate ms p50 {:.2} p99 {:.2}; \
             snapshot {} bytes, encode {:.2} ms, {} not published; map {} leaves, {} bytes",
            w.frames_received, w.frames_integrated, w.frames_dropped, w.frames_rejected, w.points_integrated, w.points_skipped,
            w.integrate_ms_p50, w.integrate_ms_p99, w.snapshot_bytes, w.encode_ms_last, self.publish_failures, w.map_leaves, w.map_memory_bytes
        )
    }
}

/// Where snapshots cover the map.
#[derive(Debug, Clone, Copy, PartialEq)]
enum ScopeSetting {
    Whole,
    AroundSensor([f64; 3]),
    Fixed([f64; 3], [f64; 3]),
}

impl ScopeSetting {
    fn from_request(r: &ControlRequest) -> Result<Self, String> {
        let s = r.scope;
        if !s.iter().all(|c| c.is_finite()) {
            return Err("scope values must be finite".into());
        }
        match r.scope_kind {
            0 => Ok(Self::Whole),
            1 if s[..3].iter().all(|&h| h > 0.0) => Ok(Self::AroundSensor([s[0], s[1], s[2]])),
            1 => Err("half extents must be > 0".into()),
            2 if (0..3).all(|k| s[k] <= s[k + 3]) => {
                Ok(Self::Fixed([s[0], s[1], s[2]], [s[3], s[4], s[5]]))
            }
            2 => Err("box min must not exceed max".into()),
            k => Err(format!("unknown scope kind {k}")),
        }
    }

    fn scope(&self, sensor: [f64; 3]) -> Scope {
        match *self {
            Self::Whole => Scope::Whole,
            Self::AroundSensor(h) => Scope::Box {
                min: [0, 1, 2].map(|k| sensor[k] - h[k]),
                max: [0, 1, 2].map(|k| sensor[k] + h[k]),
            },
            Self::Fixed(min, max) => Scope::Box { min, max },
        }
    }
}

pub fn run(a: ServeArgs) -> Result<()> {
    let cfg = a.resolve()?;
    let names = ServiceNames::new(&cfg.prefix, &cfg.map);
    let node = NodeBuilder::new()
        .name(&NodeName::new("voxmap-serve").map_err(|e| anyhow!("{e:?}"))?)
        .config(&Config::default())
        .signal_handling_mode(SignalHandlingMode::HandleTerminationRequests)
        .create::<ipc::Service>()
        .map_err(|e| anyhow!("creating iceoryx2 node: {e:?}"))?;
    let cleanup = node.try_cleanup_dead_nodes();
    eprintln!("voxmap serve: dead iceoryx2 nodes cleaned up: {cleanup:?}");
    let queue = cfg.intake == "queue";
    let frames = open_frames(&node, &names)?
        .subscriber_builder()
        .buffer_size(if queue {
            cfg.queue_depth
        } else {
            qos::FRAME_SUBSCRIBER_BUFFER
        })
        .create()
        .map_err(|e| anyhow!("frame subscriber: {e:?}"))?;
    let frame_events = open_event(&node, &names.frames_event)?
        .listener_builder()
        .create()
        .map_err(|e| anyhow!("frame listener: {e:?}"))?;
    let snapshots = open_snapshots(&node, &names)?
        .publisher_builder()
        .initial_max_slice_len(1 << 20)
        .allocation_strategy(AllocationStrategy::PowerOfTwo)
        .create()
        .map_err(|e| anyhow!("snapshot publisher: {e:?}"))?;
    let snapshot_events = open_event(&node, &names.snapshot_event)?
        .notifier_builder()
        .create()
        .map_err(|e| anyhow!("snapshot notifier: {e:?}"))?;
    let control = open_control(&node, &names)?
        .server_builder()
        .create()
        .map_err(|e| anyhow!("control server: {e:?}"))?;

    let mut map = match &a.load {
        Some(p) => mapfile::load_map(p)?,
        None => cfg.new_map()?,
    };
    let threads = cfg.threads();
    let mut integ = cfg.integrator()?;
    // After the integration pool exists, so only this (I/O) thread runs real-time.
    if cfg.rt_priority > 0 {
        crate::os::set_realtime(cfg.rt_priority)?;
    }
    let mut stats = Stats::default();
    let mut sequence = 0u64;
    // Time stamp of the data in the map: the last integrated frame's (or now, before any).
    let mut stamp_ns = now_ns();

    let mut scope = ScopeSetting::Whole;
    let mut sensor = [0.0f64; 3];
    let try_publish = |integ: &Integrator,
                       map: &OccupancyMap,
                       sequence: u64,
                       stamp_ns: u64,
                       stats: &mut Stats,
                       scope: Scope|
     -> Result<()> {
        let t = Instant::now();
        let meta = Meta {
            sequence,
            timestamp_ns: stamp_ns,
            with_values: cfg.snapshot_values,
        };
        let plan = integ.install(|| Plan::new(map, scope, meta));
        let n = plan.encoded_len();
        let mut sample = snapshots
            .loan_slice(n)
            .map_err(|e| anyhow!("loaning {n} bytes for a snapshot: {e:?}"))?;
        let payload = sample.payload_mut();
        integ.install(|| plan.write(payload))?;
        *sample.user_header_mut() = SnapshotHeader {
            version: SNAPSHOT_WIRE_VERSION,
            reserved: 0,
            sequence,
            len: n as u64,
            published_ns: now_ns(),
        };
        sample
            .send()
            .map_err(|e| anyhow!("sending snapshot: {e:?}"))?;
        snapshot_events
            .notify()
            .map_err(|e| anyhow!("notify: {e:?}"))?;
        stats.last_snapshot_bytes = n;
        stats.sequence = sequence;
        stats.last_encode_ms = t.elapsed().as_secs_f64() * 1e3;
        Ok(())
    };
    // A snapshot that cannot be published (no shared memory left, a map too large for
    // one snapshot) is logged and counted; the service keeps integrating.
    let publish = |integ: &Integrator,
                   map: &OccupancyMap,
                   sequence: u64,
                   stamp_ns: u64,
                   stats: &mut Stats,
                   scope: Scope| {
        if let Err(e) = try_publish(integ, map, sequence, stamp_ns, stats, scope) {
            stats.publish_failures += 1;
            eprintln!("voxmap serve: snapshot {sequence} not published: {e:#}");
        }
    };
    publish(
        &integ,
        &map,
        sequence,
        stamp_ns,
        &mut stats,
        scope.scope(sensor),
    );
    eprintln!(
        "voxmap serve: prefix '{}', map '{}', resolution {} m, max range {} m, mode {}, {threads} threads, intake {}; frames on '{}'",
        cfg.prefix, cfg.map, map.resolution(), cfg.max_range, cfg.mode, cfg.intake, names.frames
    );

    let waitset = WaitSetBuilder::new()
        .signal_handling_mode(SignalHandlingMode::HandleTerminationRequests)
        .create::<ipc::Service>()
        .map_err(|e| anyhow!("waitset: {e:?}"))?;
    let frame_guard = waitset
        .attach_notification(&frame_events)
        .map_err(|e| anyhow!("attach: {e:?}"))?;
    let tick = waitset
        .attach_interval(Duration::from_millis(200))
        .map_err(|e| anyhow!("attach: {e:?}"))?;
    let mut files = FileWorker::spawn().context("starting the file worker")?;
    // Control requests whose file job is running, in the order of the jobs.
    let mut waiting = std::collections::VecDeque::new();
    // Control requests that came while a file job ran, in order.
    let mut deferred = std::collections::VecDeque::new();
    let started = Instant::now();
    let mut last_log = Instant::now();
    let interval = Duration::from_secs_f64(cfg.snapshot_interval_ms / 1e3);
    let mut last_publish = Instant::now();
    // Integrated frames not yet in a published snapshot (under snapshot_interval_ms).
    let mut unpublished = false;
    // Last sequence seen per publisher, to count frames the queue dropped.
    let mut last_seq: std::collections::HashMap<_, u64> = std::collections::HashMap::new();
    loop {
        let (mut frames_ready, mut ticked) = (false, false);
        let timeout = if unpublished {
            interval.saturating_sub(last_publish.elapsed())
        } else {
            Duration::from_secs(1)
        };
        let r = waitset
            .wait_and_process_once_with_timeout(
                |id| {
                    if id.has_event_from(&frame_guard) {
                        frames_ready = true;
                    }
                    if id.has_event_from(&tick) {
                        ticked = true;
                    }
                    CallbackProgression::Continue
                },
                timeout,
            )
            .map_err(|e| anyhow!("waitset: {e:?}"))?;
        if matches!(
            r,
            WaitSetRunResult::TerminationRequest | WaitSetRunResult::Interrupt
        ) {
            break;
        }
        if frames_ready {
            frame_events
                .try_wait(|_| {})
                .map_err(|e| anyhow!("listener: {e:?}"))?;
        }
        loop {
            // Latest wins: take everything waiting, integrate the newest. Queue: integrate
            // waiting frames one by one, in order; the subscriber's buffer of queue_depth
            // drops the oldest on overflow, which shows as a gap in a publisher's sequence.
            let mut next = None;
            while let Some(s) = frames
                .receive()
                .map_err(|e| anyhow!("receive frame: {e:?}"))?
            {
                stats.received += 1;
                let stamp = s.user_header().timestamp_ns;
                if stamp != 0 {
                    Stats::record(
                        &mut stats.intake_us,
                        now_ns().saturating_sub(stamp) as f64 / 1e3,
                    );
                }
                let seq = s.user_header().sequence;
                if let Some(prev) = last_seq.insert(s.header().publisher_id(), seq) {
                    // The sequence is the publisher's word: no arithmetic on it may overflow.
                    if queue && seq > prev.saturating_add(1) {
                        stats.dropped = stats.dropped.saturating_add(seq - prev - 1);
                    }
                }
                if next.replace(s).is_some() {
                    stats.dropped += 1;
                }
                if queue {
                    break;
                }
            }
            let Some(s) = next else { break };
            let h = *s.user_header();
            let outcome = h
                .validate(s.payload().len())
                .map_err(|e| e.to_string())
                .and_then(|pose| {
                    let frame = Frame {
                        pose,
                        points: s.payload(),
                    };
                    integ
                        .integrate(&mut map, &frame)
                        .map(|rep| (pose, rep))
                        .map_err(|e| e.to_string())
                });
            drop(s);
            match outcome {
                Err(why) => {
                    stats.rejected += 1;
                    eprintln!("voxmap serve: frame {} rejected: {why}", h.sequence);
                }
                Ok((pose, rep)) => {
                    stats.integrated += 1;
                    stats.points += rep.points;
                    stats.skipped_points += rep.skipped_nonfinite;
                    Stats::record(
                        &mut stats.integrate_ms,
                        rep.times.total().as_secs_f64() * 1e3,
                    );
                    sequence = h.sequence;
                    stamp_ns = if h.timestamp_ns != 0 {
                        h.timestamp_ns
                    } else {
                        now_ns()
                    };
                    sensor = pose.translation.vector.into();
                    unpublished = true;
                }
            }
            if !queue {
                break;
            }
        }
        if unpublished && last_publish.elapsed() >= interval {
            publish(
                &integ,
                &map,
                sequence,
                stamp_ns,
                &mut stats,
                scope.scope(sensor),
            );
            last_publish = Instant::now();
            unpublished = false;
        }
        // Control requests: answered here, between frames; a bad request gets an error.
        // While a save or load runs, requests other than stats wait for it, in order: they
        // then see the map as it leaves the file job, and one save at a time holds a copy.
        // A finished file job is answered first (a loaded map swapped in), then requests
        // deferred behind it, then new ones.
        loop {
            let (req, (ok, msg, republish)) = if let Some(done) = files.try_done() {
                let req = waiting
                    .pop_front()
                    .expect("one waiting request per file job");
                (req, finish_file_job(done, &mut map, &integ))
            } else {
                let next = match waiting.is_empty() {
                    true => deferred.pop_front(),
                    false => None,
                };
                let req = match next {
                    Some(req) => req,
                    None => match control
                        .receive()
                        .map_err(|e| anyhow!("control receive: {e:?}"))?
                    {
                        Some(req) => req,
                        None => break,
                    },
                };
                let r = *req.payload();
                if !waiting.is_empty() && r.kind != ControlKind::Stats as u32 {
                    deferred.push_back(req);
                    continue;
                }
                let answer = match r.kind {
                    k if k == ControlKind::Stats as u32 => (true, String::new(), false),
                    // Saves and loads run on the file worker; their answers go out when done.
                    k if k == ControlKind::Save as u32 || k == ControlKind::Load as u32 => {
                        match r.path() {
                            None => (false, "bad path".to_string(), false),
                            Some(p) => {
                                let path = p.into();
                                let job = if k == ControlKind::Save as u32 {
                                    let file = integ.install(|| mapfile::encode_map_parts(&map));
                                    Job::Save { path, file }
                                } else {
                                    Job::Load { path }
                                };
                                match files.submit(job) {
                                    Ok(()) => {
                                        waiting.push_back(req);
                                        continue;
                                    }
                                    Err(e) => (false, e, false),
                                }
                            }
                        }
                    }
                    k if k == ControlKind::Clear as u32 => {
                        map.clear();
                        (true, "cleared".to_string(), true)
                    }
                    k if k == ControlKind::SetScope as u32 => {
                        match ScopeSetting::from_request(&r) {
                            Ok(s) => {
                                scope = s;
                                (true, format!("scope {s:?}"), true)
                            }
                            Err(e) => (false, e, false),
                        }
                    }
                    k => (false, format!("unknown request kind {k}"), false),
                };
                (req, answer)
            };
            if !ok {
                eprintln!("voxmap serve: control request failed: {msg}");
            }
            if republish {
                publish(
                    &integ,
                    &map,
                    sequence,
                    stamp_ns,
                    &mut stats,
                    scope.scope(sensor),
                );
                last_publish = Instant::now();
                unpublished = false;
            }
            let _ = req.send_copy(ControlResponse::new(ok, &msg, stats.wire(&map)));
        }
        if ticked {
            // Late joiners get the history sample only when the publisher updates.
            let _ = snapshots.update_connections();
        }
        if last_log.elapsed() >= Duration::from_secs(5) {
            last_log = Instant::now();
            eprintln!("voxmap serve: {}", stats.log_line(&map));
        }
        if a.exit_after > 0.0 && started.elapsed().as_secs_f64() >= a.exit_after {
            break;
        }
    }
    // A save being written is finished and answered; a load is not waited for (nor
    // swapped in if it is done), and requests still deferred are refused.
    let mut finished = files.finish().into_iter();
    for req in waiting.into_iter().chain(deferred) {
        let (ok, msg, _) = match finished.next() {
            Some(Done::Loaded(_, Ok(_))) | None => {
                (false, "not done: the service is exiting".to_string(), false)
            }
            Some(done) => finish_file_job(done, &mut map, &integ),
        };
        let _ = req.send_copy(ControlResponse::new(ok, &msg, stats.wire(&map)));
    }
    publish(
        &integ,
        &map,
        sequence,
        stamp_ns,
        &mut stats,
        scope.scope(sensor),
    );
    if let Some(p) = &a.save_on_exit {
        mapfile::save_map(&map, p).with_context(|| format!("saving map to {}", p.display()))?;
        eprintln!("voxmap serve: map saved to {}", p.display());
    }
    eprintln!("voxmap serve: exiting; {}", stats.log_line(&map));
    Ok(())
}

/// Apply a finished file job: a loaded map replaces `map` unless the integrator cannot
/// work at its resolution. Returns the answer (ok, message, republish).
fn finish_file_job(done: Done, map: &mut OccupancyMap, integ: &Integrator) -> (bool, String, bool) {
    match done {
        Done::Saved(p, Ok(())) => (true, format!("saved to {}", p.display()), false),
        Done::Loaded(p, Ok(m)) => {
            if !integ.fits_resolution(m.resolution()) {
                let why = format!(
                    "{} not loaded: at its resolution of {} m, max range {} m spans more than {} voxels",
                    p.display(),
                    m.resolution(),
                    integ.config().max_range,
                    voxmap_core::integrate::MAX_RANGE_VOXELS
                );
                return (false, why, false);
            }
            *map = m;
            (true, format!("loaded {}", p.display()), true)
        }
        Done::Saved(_, Err(e)) | Done::Loaded(_, Err(e)) => (false, e, false),
    }
}

/// The `p` quantile (0..=1, nearest rank) of ascending `sorted`; 0 when empty.
pub fn percentile(sorted: &[f64], p: f64) -> f64 {
    sorted
        .get(((sorted.len() as f64 - 1.0) * p).round() as usize)
        .copied()
        .unwrap_or(0.0)
}

//! `voxmap serve`: the mapping daemon. Frames in over iceoryx2 ([`intake`]), integrated
//! on a thread pool, snapshots out, encoded straight into loaned shared-memory samples
//! ([`publish`]); control requests answered between frames ([`control`]); counters in
//! [`stats`]. This file sets it up and runs the event loop.

mod control;
mod intake;
mod publish;
mod stats;

use crate::config::{Config, Intake, MappingArgs};
use crate::os::now_ns;
use anyhow::{anyhow, bail, Context, Result};
use clap::Args;
use iceoryx2::prelude::*;
use iceoryx2::waitset::WaitSetRunResult;
use std::path::PathBuf;
use std::time::{Duration, Instant};
use voxmap_ipc::ports::{self, open_control, open_event, open_frames, open_snapshots, qos};
use voxmap_ipc::{MapScope, ServiceNames};
use voxmap_map::field::DistanceField;
use voxmap_map::io::mapfile;
use voxmap_map::mapper::{FieldAfterLoad, ReplaceError};
use voxmap_map::snapshot::Scope;
use voxmap_map::{Mapper, OccupancyMap};

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
    /// Resume from this map file (its resolution and sensor model replace the configured),
    /// or continue the tile store in this directory (as --store).
    #[arg(long)]
    pub load: Option<PathBuf>,
    /// With a tile store: save it this often (seconds) when frames came since; 0 = only on
    /// request and at exit (`store_save_interval_s`, default 60).
    #[arg(long, value_name = "SECONDS")]
    pub store_save_interval: Option<f64>,
    /// Save the map here on SIGINT/SIGTERM.
    #[arg(long)]
    pub save_on_exit: Option<PathBuf>,
    /// Include per-voxel log-odds in snapshots (512 bytes per leaf).
    #[arg(long)]
    pub snapshot_values: bool,
    /// Publish at most one snapshot per this many milliseconds (0 = after every frame).
    #[arg(long)]
    pub snapshot_interval_ms: Option<f64>,
    /// Frames arriving faster than they integrate: the newest wins, or a queue.
    #[arg(long, value_enum)]
    pub intake: Option<Intake>,
    /// Frames kept waiting under --intake queue (1..=4).
    #[arg(long)]
    pub queue_depth: Option<usize>,
    /// Run the frame/snapshot thread under SCHED_FIFO at this priority (1..=99; 0 = off).
    #[arg(long)]
    pub rt_priority: Option<i32>,
    /// Exit after this many seconds (for demos and tests); 0 = run until a signal.
    #[arg(long, default_value_t = 0.0)]
    pub exit_after: f64,
    /// Also speak ROS 2 over DDS: clouds and TF in, the map out (see `[ros2]` in the config).
    #[arg(long)]
    pub ros2: bool,
    /// A PointCloud2 topic to map, `TOPIC` or `TOPIC@MAX_RANGE`; repeatable; replaces the
    /// config's `ros2.cloud_topics`.
    #[arg(long = "ros2-cloud-topic", value_name = "TOPIC")]
    pub ros2_cloud_topics: Vec<voxmap_ros2::CloudTopic>,
    /// The frame the map is built in (default `map`).
    #[arg(long)]
    pub ros2_map_frame: Option<String>,
}

impl ServeArgs {
    /// The configuration with this command's own flags applied.
    pub fn resolve(&self) -> Result<crate::config::Config> {
        let mut c = self.mapping.resolve()?;
        // A tile store given to --load is continued as --store.
        if let Some(p) = self.load.as_ref().filter(|p| p.is_dir()) {
            if !c.store.is_empty() && std::path::Path::new(&c.store) != p.as_path() {
                bail!(
                    "--load {} is a tile store and --store names another",
                    p.display()
                );
            }
            c.store = p.to_string_lossy().into_owned();
            c.check()?;
        }
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
        if let Some(v) = self.intake {
            c.intake = v;
        }
        if let Some(v) = self.store_save_interval {
            c.store_save_interval_s = v;
            c.check()?;
        }
        if let Some(v) = self.queue_depth {
            c.queue_depth = v;
        }
        if let Some(v) = self.rt_priority {
            c.rt_priority = v;
        }
        if !self.ros2_cloud_topics.is_empty() {
            c.ros2.cloud_topics = self.ros2_cloud_topics.clone();
        }
        if let Some(f) = &self.ros2_map_frame {
            c.ros2.map_frame = f.clone();
        }
        c.check()?;
        Ok(c)
    }
}

/// The map and what the loop knows about it.
pub(crate) struct MapState {
    mapper: Mapper,
    /// When the service started: the time stamp of its snapshots before any frame.
    started_ns: u64,
    scope: MapScope,
    stats: stats::Stats,
}

impl MapState {
    /// Sequence number of the last integrated frame (0 before any).
    fn sequence(&self) -> u64 {
        self.mapper.last_frame().sequence
    }

    /// Time stamp of the data in the map: the last integrated frame's (or the service's
    /// start, before any).
    fn stamp_ns(&self) -> u64 {
        match self.mapper.sensor() {
            Some(_) => self.mapper.last_frame().stamp_ns,
            None => self.started_ns,
        }
    }

    /// The last integrated frame's sensor position, for `MapScope::AroundSensor`.
    fn sensor(&self) -> [f64; 3] {
        self.mapper.sensor().map_or([0.0; 3], |p| p.coords.into())
    }

    /// Put a loaded map in, with the field its file carried; logs what became of the
    /// distance field.
    fn load(
        &mut self,
        map: OccupancyMap,
        carried: Option<DistanceField>,
    ) -> Result<(), ReplaceError> {
        match self.mapper.replace_map(map, carried)?.1 {
            FieldAfterLoad::None => {}
            FieldAfterLoad::Carried { band_voxels } => eprintln!(
                "voxmap serve: distance field read with the map ({band_voxels} voxels in the band)"
            ),
            FieldAfterLoad::Rebuilt(r) => eprintln!(
                "voxmap serve: distance field built in {:.1} ms ({} patches, {} voxels in the band)",
                r.time.as_secs_f64() * 1e3,
                r.patches,
                self.mapper.field().map_or(0, |f| f.band_voxels())
            ),
        }
        Ok(())
    }

    /// What the next snapshot covers. A window's tiles are brought back from the tile
    /// store first; under a memory budget the whole map's snapshot holds the tiles in
    /// memory.
    fn snapshot_scope(&mut self) -> Scope {
        match self.scope.bounds(self.sensor()) {
            None => Scope::Whole,
            Some((min, max)) => {
                let r = self.mapper.load_region(min.into(), max.into());
                for e in r.iter().flat_map(|r| &r.refused) {
                    eprintln!("voxmap serve: tile store: {e}; its region reads as unknown");
                }
                Scope::Box { min, max }
            }
        }
    }
}

/// The service's iceoryx2 ports: frames in and their wake-up, snapshots out, control.
struct Ports {
    intake: intake::FrameIntake,
    frame_events: iceoryx2::port::listener::Listener<ipc::Service>,
    out: publish::SnapshotOut,
    control: control::Control,
}

impl Ports {
    fn open(node: &Node<ipc::Service>, names: &ServiceNames, cfg: &Config) -> Result<Self> {
        let subscriber = open_frames(node, names)?
            .subscriber_builder()
            .buffer_size(match cfg.intake {
                Intake::Queue => cfg.queue_depth,
                Intake::Latest => qos::FRAME_SUBSCRIBER_BUFFER,
            })
            .create()
            .map_err(|e| anyhow!(e).context("creating the frame subscriber"))?;
        let frame_events = open_event(node, &names.frames_event)?
            .listener_builder()
            .create()
            .map_err(|e| anyhow!(e).context("creating the frame listener"))?;
        let out = publish::SnapshotOut {
            publisher: open_snapshots(node, names)?
                .publisher_builder()
                .initial_max_slice_len(1 << 20)
                .allocation_strategy(AllocationStrategy::PowerOfTwo)
                .create()
                .map_err(|e| anyhow!(e).context("creating the snapshot publisher"))?,
            notifier: open_event(node, &names.snapshot_event)?
                .notifier_builder()
                .create()
                .map_err(|e| anyhow!(e).context("creating the snapshot notifier"))?,
            with_values: cfg.snapshot_values,
        };
        let control = control::Control::new(
            open_control(node, names)?
                .server_builder()
                .create()
                .map_err(|e| anyhow!(e).context("creating the control server"))?,
        )?;
        Ok(Ports {
            intake: intake::FrameIntake::new(subscriber, cfg.intake),
            frame_events,
            out,
            control,
        })
    }
}

/// The tile store's saves between requests: every `store_save_interval_s` when frames
/// were integrated since the last one.
struct StoreSaves {
    every: Option<Duration>,
    last: Instant,
    /// Frames integrated when the last save began.
    covered: u64,
}

impl StoreSaves {
    fn new(every_s: f64) -> Self {
        Self {
            every: (every_s > 0.0).then(|| Duration::from_secs_f64(every_s)),
            last: Instant::now(),
            covered: 0,
        }
    }

    /// Save if one is due, the map is kept in a store, and frames came since the last
    /// save; a failure is logged (the tiles stay in memory, the next save tries again).
    fn when_due(&mut self, s: &mut MapState) {
        let Some(every) = self.every else { return };
        let integrated = s.stats.integrated;
        if self.last.elapsed() < every || integrated == self.covered {
            return;
        }
        self.last = Instant::now();
        match s.mapper.save_store() {
            Some(Ok(_)) => self.covered = integrated,
            Some(Err(e)) => eprintln!("voxmap serve: saving the tile store: {e}"),
            None => {}
        }
    }
}

pub fn run(a: ServeArgs) -> Result<()> {
    let cfg = a.resolve()?;
    // Checked before anything is opened: a bad variable stops the start.
    let discovery = match a.ros2 {
        true => Some(voxmap_ros2::discovery::Discovery::from_env()?),
        false => None,
    };
    let names = ServiceNames::new(&cfg.prefix, &cfg.map);
    let node = ports::node(
        "voxmap-serve",
        SignalHandlingMode::HandleTerminationRequests,
    )?;
    let cleanup = node.try_cleanup_dead_nodes();
    eprintln!("voxmap serve: dead iceoryx2 nodes cleaned up: {cleanup:?}");
    let Ports {
        mut intake,
        frame_events,
        out,
        mut control,
    } = Ports::open(&node, &names, &cfg)?;
    let mut s = MapState {
        mapper: cfg.mapper()?,
        started_ns: now_ns(),
        scope: MapScope::Whole,
        stats: stats::Stats::default(),
    };
    s.stats.kernel = s.mapper.integrator().kernel().name();
    if let Some(p) = a.load.as_ref().filter(|p| !p.is_dir()) {
        if s.mapper.store_dir().is_some() {
            bail!("--load {}: a map file does not load into a tile store; export the store, or start without --store", p.display());
        }
        let (map, carried) = mapfile::load_map_with_field(p)?;
        s.load(map, carried)
            .with_context(|| format!("{} not loaded", p.display()))?;
    }
    // After the integration pool exists, so only this (I/O) thread runs real-time.
    if cfg.rt_priority > 0 {
        crate::os::set_realtime(cfg.rt_priority)?;
    }
    out.publish(&mut s);
    log_start(&cfg, &names, &s);
    let bridge = match discovery {
        None => None,
        Some(d) => Some(voxmap_ros2::Bridge::start(
            cfg.ros2.clone(),
            d,
            &cfg.prefix,
            &cfg.map,
        )?),
    };

    let waitset = WaitSetBuilder::new()
        .signal_handling_mode(SignalHandlingMode::HandleTerminationRequests)
        .create::<ipc::Service>()
        .map_err(|e| anyhow!(e).context("creating the waitset"))?;
    let frame_guard = waitset
        .attach_notification(&frame_events)
        .map_err(|e| anyhow!(e).context("attaching the frame listener"))?;
    let tick = waitset
        .attach_interval(Duration::from_millis(200))
        .map_err(|e| anyhow!(e).context("attaching the tick"))?;
    let started = Instant::now();
    let mut last_log = Instant::now();
    let mut store_saves = StoreSaves::new(cfg.store_save_interval_s);
    let interval = Duration::from_secs_f64(cfg.snapshot_interval_ms / 1e3);
    let mut last_publish = Instant::now();
    // Integrated frames not yet in a published snapshot (under snapshot_interval_ms).
    let mut unpublished = false;
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
                    frames_ready |= id.has_event_from(&frame_guard);
                    ticked |= id.has_event_from(&tick);
                    CallbackProgression::Continue
                },
                timeout,
            )
            .map_err(|e| anyhow!(e).context("waiting for events"))?;
        if matches!(
            r,
            WaitSetRunResult::TerminationRequest | WaitSetRunResult::Interrupt
        ) {
            break;
        }
        if frames_ready {
            frame_events
                .try_wait(|_| {})
                .map_err(|e| anyhow!(e).context("taking frame events"))?;
        }
        unpublished |= intake.integrate_waiting(&mut s)?;
        if unpublished && last_publish.elapsed() >= interval {
            out.publish(&mut s);
            last_publish = Instant::now();
            unpublished = false;
        }
        control.serve(&mut s, |s| {
            out.publish(s);
            last_publish = Instant::now();
            unpublished = false;
        })?;
        if ticked {
            out.update_connections();
            store_saves.when_due(&mut s);
        }
        if last_log.elapsed() >= Duration::from_secs(5) {
            last_log = Instant::now();
            eprintln!("voxmap serve: {}", s.stats.log_line(&s.mapper));
            if let Some(b) = &bridge {
                eprintln!("voxmap serve: {}", b.counters.line());
            }
        }
        if bridge.as_ref().is_some_and(|b| b.has_ended()) {
            break;
        }
        if a.exit_after > 0.0 && started.elapsed().as_secs_f64() >= a.exit_after {
            break;
        }
    }
    let bridge_end = bridge.map(|b| {
        let line = b.counters.line();
        (b.stop(), line)
    });
    control.finish(&mut s);
    out.publish(&mut s);
    if let Some(r) = s.mapper.save_store() {
        let r = r.context("saving the tile store")?;
        eprintln!(
            "voxmap serve: tile store saved ({} tiles written, generation {})",
            r.tiles_written, r.generation
        );
    }
    if let Some(p) = &a.save_on_exit {
        s.mapper
            .write_map_file(p)
            .with_context(|| format!("saving map to {}", p.display()))?;
        eprintln!("voxmap serve: map saved to {}", p.display());
    }
    eprintln!("voxmap serve: exiting; {}", s.stats.log_line(&s.mapper));
    if let Some((end, line)) = bridge_end {
        eprintln!("voxmap serve: exiting; {line}");
        end.context("the ROS 2 bridge failed")?;
    }
    Ok(())
}

fn log_start(cfg: &Config, names: &ServiceNames, s: &MapState) {
    let field = match s.mapper.field() {
        None => String::new(),
        Some(f) => format!(
            ", distance field to {} m (unknown {}{})",
            f.max_distance(),
            f.config().unknown.name(),
            f.config()
                .window
                .map_or(String::new(), |w| format!(", window ±{w:?} m"))
        ),
    };
    let store = match (s.mapper.store_dir(), s.mapper.tile_stats()) {
        (Some(d), Some(t)) => format!(
            ", tile store {} ({} tiles stored, last frame {}), memory budget {}",
            d.display(),
            t.tiles_stored,
            s.mapper.last_frame().sequence,
            t.memory_budget
                .map_or("unlimited".to_string(), |b| format!("{} MiB", b >> 20))
        ),
        _ => String::new(),
    };
    eprintln!(
        "voxmap serve: prefix '{}', map '{}', resolution {} m, max range {} m, mode {}, {} threads, kernel {}, intake {}{field}{store}; frames on '{}'",
        cfg.prefix,
        cfg.map,
        s.mapper.map().resolution(),
        cfg.max_range,
        cfg.ray_mode().name(),
        cfg.threads(),
        s.mapper.integrator().kernel().name(),
        cfg.intake,
        names.frames
    );
}

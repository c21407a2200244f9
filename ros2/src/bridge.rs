//! The bridge's loop, on a thread of its own: ROS 2 clouds and TF in through the tf2-style
//! [`CloudSync`] (shared with bag replay), posed clouds out to the service as frames; the
//! newest snapshot out as the three map topics at most every `publish_period_ms`; the
//! `/voxmap/` services answered through the service's control port and snapshots.

use crate::config::{Ros2Config, ServiceMappingName};
use crate::discovery::Discovery;
use crate::interfaces::{
    Outcome, PathRequest, RaytraceRequest, RaytraceResponse, TriggerRequest, NAMESPACE,
};
use crate::outputs;
use anyhow::{anyhow, Context as _, Result};
use ros2_client::dds::rustdds::mio1::{Events, Interest, Poll, Token};
use ros2_client::dds::rustdds::{DomainParticipant, Topic, TopicDescription};
use ros2_client::dds::{Context, Node, Publisher, Server, ServiceMapping, Subscription};
use ros2_client::qos::{Durability, History, Liveliness, Reliability, WhenFull};
use ros2_client::{MessageTypeName, Name, NodeName, NodeOptions, QosProfile, ServiceTypeName};
use serde_bytes::ByteBuf;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering::Relaxed};
use std::sync::Arc;
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};
use voxmap_client::{error_chain, FramePublisher, MapControl, SnapshotSubscriber, WorldPoint};
use voxmap_ros::msg::{OccupancyGrid, Octomap, PointCloud2, TfMessage, Vector3};
use voxmap_ros::sync::{CloudSync, DropReason, PosedCloud, SyncConfig};

/// What the bridge counted, readable while it runs.
#[derive(Debug, Default)]
pub struct BridgeCounters {
    /// PointCloud2 messages received (malformed ones included).
    pub clouds_received: AtomicU64,
    /// Clouds posed and handed to the service as frames.
    pub clouds_sent: AtomicU64,
    /// Clouds dropped because their transform did not come within `tf_timeout_ms`.
    pub clouds_no_tf: AtomicU64,
    /// Clouds that are not a valid PointCloud2 (undecodable, or fields or sizes wrong).
    pub clouds_malformed: AtomicU64,
    /// Posed clouds the service's frame port did not take.
    pub clouds_not_sent: AtomicU64,
    /// Transforms from `/tf` and `/tf_static` the TF buffer refused (or undecodable).
    pub tf_rejected: AtomicU64,
    /// Snapshots published as the three map topics.
    pub outputs_published: AtomicU64,
    pub output_failures: AtomicU64,
    /// Microseconds the last output took to encode and hand to DDS (the three topics).
    pub last_output_us: AtomicU64,
    pub service_calls: AtomicU64,
}

impl BridgeCounters {
    /// One line for the service's log.
    pub fn line(&self) -> String {
        let g = |c: &AtomicU64| c.load(Relaxed);
        format!(
            "ros2: {} clouds received, {} integrated, {} without a transform, {} malformed, {} not sent; {} transforms rejected; {} map outputs ({} failed, last {:.1} ms); {} service calls",
            g(&self.clouds_received),
            g(&self.clouds_sent),
            g(&self.clouds_no_tf),
            g(&self.clouds_malformed),
            g(&self.clouds_not_sent),
            g(&self.tf_rejected),
            g(&self.outputs_published),
            g(&self.output_failures),
            g(&self.last_output_us) as f64 / 1e3,
            g(&self.service_calls),
        )
    }
}

/// A running bridge: stop it with [`Bridge::stop`].
pub struct Bridge {
    thread: Option<std::thread::JoinHandle<Result<()>>>,
    stop: Arc<AtomicBool>,
    pub counters: Arc<BridgeCounters>,
}

impl Bridge {
    /// Start the bridge to the service `prefix`/`map`, which must be running (its ports
    /// exist). Returns once the DDS entities and the service's ports are open, or with
    /// what failed.
    pub fn start(cfg: Ros2Config, discovery: Discovery, prefix: &str, map: &str) -> Result<Self> {
        cfg.check().map_err(|e| anyhow!(e))?;
        let stop = Arc::new(AtomicBool::new(false));
        let counters = Arc::new(BridgeCounters::default());
        let (ready_tx, ready_rx) = std::sync::mpsc::channel::<Result<(), String>>();
        let (prefix, map) = (prefix.to_string(), map.to_string());
        let (st, ct) = (stop.clone(), counters.clone());
        let thread = std::thread::Builder::new()
            .name("voxmap-ros2".into())
            .spawn(move || {
                lower_priority();
                // iceoryx2's ports are not Send: everything is made on this thread.
                let mut b = match Loop::new(cfg, &discovery, &prefix, &map, ct) {
                    Ok(b) => {
                        let _ = ready_tx.send(Ok(()));
                        b
                    }
                    Err(e) => {
                        let _ = ready_tx.send(Err(format!("{e:#}")));
                        return Ok(());
                    }
                };
                b.run(&st)
            })
            .context("starting the ROS 2 thread")?;
        match ready_rx.recv() {
            Ok(Ok(())) => Ok(Self {
                thread: Some(thread),
                stop,
                counters,
            }),
            Ok(Err(e)) => {
                let _ = thread.join();
                Err(anyhow!(e).context("starting the ROS 2 bridge"))
            }
            Err(_) => Err(anyhow!("the ROS 2 bridge's thread ended while starting")),
        }
    }

    /// Whether the bridge's thread has ended (an error it met, or a panic).
    pub fn has_ended(&self) -> bool {
        self.thread.as_ref().is_none_or(|t| t.is_finished())
    }

    /// Stop the bridge and wait for it; the error that ended it, if any.
    pub fn stop(mut self) -> Result<()> {
        self.stop.store(true, Relaxed);
        match self.thread.take().map(|t| t.join()) {
            None => Ok(()),
            Some(Ok(r)) => r,
            Some(Err(_)) => Err(anyhow!("the ROS 2 bridge panicked")),
        }
    }
}

impl Drop for Bridge {
    fn drop(&mut self) {
        self.stop.store(true, Relaxed);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

/// Run this thread (and the DDS threads it starts, which inherit it) at nice 10, so that
/// encoding the map topics yields the CPUs to the integration threads.
fn lower_priority() {
    #[cfg(target_os = "linux")]
    {
        // SAFETY: gettid has no preconditions; setpriority(PRIO_PROCESS, tid, 10) changes
        // only the nice value of this thread and reads no memory of ours. A failure (it
        // cannot fail for a higher nice value) would leave the priority as it was.
        unsafe {
            let tid = libc::gettid();
            libc::setpriority(libc::PRIO_PROCESS, tid as libc::id_t, 10);
        }
    }
}

fn now_ns() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| d.as_nanos() as u64)
}

/// QoS of sensor clouds: best effort, so that both sensor-QoS and reliable publishers match.
fn cloud_qos() -> QosProfile {
    QosProfile::subscription_default()
        .reliability(Reliability::BestEffort)
        .durability(Durability::Volatile)
        .history(History::KeepLast { depth: 5 })
}

/// `/tf` as tf2_ros listens: reliable, volatile, the last 100.
fn tf_qos() -> QosProfile {
    reliable(Durability::Volatile, 100)
}

fn reliable(durability: Durability, depth: usize) -> QosProfile {
    QosProfile {
        reliability: Reliability::Reliable {
            when_full: WhenFull::Wait(Duration::from_millis(100)),
        },
        durability,
        history: History::KeepLast { depth },
        deadline: None,
        lifespan: None,
        liveliness: Liveliness::Automatic,
        liveliness_lease: None,
    }
}

/// The map topics under [`NAMESPACE`] (name, package, type), in the order of [`Outputs`]'
/// fields.
const MAP_TOPICS: [(&str, &str, &str); 3] = [
    ("occupied", "sensor_msgs", "PointCloud2"),
    ("octomap_binary", "octomap_msgs", "Octomap"),
    ("grid", "nav_msgs", "OccupancyGrid"),
];

/// The map topics on `node`, latched (reliable, transient local, the last one): a late
/// RViz or MoveIt gets the current map.
fn map_topics(node: &Node) -> Result<[Topic; 3]> {
    let latched = reliable(Durability::TransientLocal, 1);
    let topic = |(base, pkg, ty): (&str, &str, &str)| {
        let name = Name::new(NAMESPACE, base).map_err(|e| anyhow!("{e:?}"))?;
        node.create_topic(&name, MessageTypeName::new(pkg, ty), &latched)
            .map_err(|e| anyhow!("{e:?}").context(format!("creating topic {NAMESPACE}/{base}")))
    };
    Ok([
        topic(MAP_TOPICS[0])?,
        topic(MAP_TOPICS[1])?,
        topic(MAP_TOPICS[2])?,
    ])
}

/// A ROS 2 node `/name` on a participant of its own that discovers as `discovery` says.
fn new_node(discovery: &Discovery, name: &str) -> Result<(Node, DomainParticipant)> {
    let participant = discovery.participant().map_err(|e| anyhow!(e))?;
    let ctx = Context::from_domain_participant(participant)
        .map_err(|e| anyhow!("{e:?}").context("creating the ROS 2 context"))?;
    let node = ctx
        .new_node(
            NodeName::new("/", name).map_err(|e| anyhow!("{e:?}"))?,
            NodeOptions::new().enable_rosout(false),
        )
        .map_err(|e| anyhow!("{e:?}").context("creating the ROS 2 node"))?;
    Ok((node, ctx.domain_participant()))
}

struct Outputs {
    occupied: Publisher<PointCloud2<ByteBuf>>,
    octomap: Publisher<Octomap>,
    grid: Publisher<OccupancyGrid>,
}

struct Services {
    save: Server<PathRequest, Outcome>,
    load: Server<PathRequest, Outcome>,
    reset: Server<TriggerRequest, Outcome>,
    raytrace: Server<RaytraceRequest, RaytraceResponse>,
}

/// One cloud topic's subscription.
struct CloudInput {
    topic: String,
    max_range: Option<f64>,
    sub: Subscription<PointCloud2<ByteBuf>>,
    /// Messages taken so far (the next one's index).
    taken: u64,
}

/// Everything the loop owns.
struct Loop {
    cfg: Ros2Config,
    counters: Arc<BridgeCounters>,
    poll: Poll,
    clouds: Vec<CloudInput>,
    tf: Subscription<TfMessage>,
    tf_static: Subscription<TfMessage>,
    outputs: Outputs,
    services: Services,
    sync: CloudSync,
    frames: FramePublisher,
    snapshots: SnapshotSubscriber,
    control: MapControl,
    /// The map topics' DDS names (`rt/voxmap/...`), in the order of [`Outputs`]' fields.
    output_names: [String; 3],
    /// `published_ns` of the snapshot last put on each map topic.
    last_output: [Option<u64>; 3],
    last_output_at: Option<Instant>,
    drops_logged: u64,
    participant: DomainParticipant,
    _node: Node,
}

impl Loop {
    fn new(
        cfg: Ros2Config,
        discovery: &Discovery,
        prefix: &str,
        map: &str,
        counters: Arc<BridgeCounters>,
    ) -> Result<Self> {
        for p in discovery.remote_static_peers() {
            eprintln!(
                "voxmap serve: ros2: static peer '{p}' is on another host: rustdds 0.15 reaches peers of this host by unicast, others only by multicast"
            );
        }
        let (mut node, participant) = new_node(discovery, &cfg.node_name)?;
        let name =
            |full: &str| Name::parse(full).map_err(|e| anyhow!("ROS 2 name '{full}': {e:?}"));
        let topic = |node: &Node, full: &str, pkg: &str, ty: &str, qos: &QosProfile| {
            node.create_topic(&name(full)?, MessageTypeName::new(pkg, ty), qos)
                .map_err(|e| anyhow!("{e:?}").context(format!("creating topic {full}")))
        };
        let poll = Poll::new().context("creating the ROS 2 poll")?;
        let mut token = 0;
        let mut next_token = || {
            token += 1;
            Token(token)
        };
        let mut clouds = Vec::new();
        for t in &cfg.cloud_topics {
            let tp = topic(&node, &t.topic, "sensor_msgs", "PointCloud2", &cloud_qos())?;
            let mut sub = node
                .create_subscription::<PointCloud2<ByteBuf>>(&tp, Some(cloud_qos()))
                .map_err(|e| anyhow!("{e:?}").context(format!("subscribing to {}", t.topic)))?;
            poll.registry()
                .register(&mut sub, next_token(), Interest::READABLE)?;
            clouds.push(CloudInput {
                topic: t.topic.clone(),
                max_range: t.max_range,
                sub,
                taken: 0,
            });
        }
        let static_qos = reliable(Durability::TransientLocal, 100);
        let tf_topic = topic(&node, "/tf", "tf2_msgs", "TFMessage", &tf_qos())?;
        let static_topic = topic(&node, "/tf_static", "tf2_msgs", "TFMessage", &static_qos)?;
        let mut tf = node
            .create_subscription::<TfMessage>(&tf_topic, Some(tf_qos()))
            .map_err(|e| anyhow!("{e:?}").context("subscribing to /tf"))?;
        let mut tf_static = node
            .create_subscription::<TfMessage>(&static_topic, Some(static_qos))
            .map_err(|e| anyhow!("{e:?}").context("subscribing to /tf_static"))?;
        poll.registry()
            .register(&mut tf, next_token(), Interest::READABLE)?;
        poll.registry()
            .register(&mut tf_static, next_token(), Interest::READABLE)?;

        let [t_occ, t_oct, t_grid] = map_topics(&node)?;
        let output_names = [&t_occ, &t_oct, &t_grid].map(|t| t.name());
        let perr = |what: &str| {
            let what = what.to_string();
            move |e| anyhow!("{e:?}").context(format!("creating the {what} publisher"))
        };
        let outputs = Outputs {
            occupied: node
                .create_publisher(&t_occ, None)
                .map_err(perr("occupied"))?,
            octomap: node
                .create_publisher(&t_oct, None)
                .map_err(perr("octomap_binary"))?,
            grid: node.create_publisher(&t_grid, None).map_err(perr("grid"))?,
        };

        let mapping = match cfg.service_mapping {
            ServiceMappingName::Enhanced => ServiceMapping::Enhanced,
            ServiceMappingName::Cyclone => ServiceMapping::Cyclone,
        };
        let sq = reliable(Durability::Volatile, 10);
        macro_rules! server {
            ($base:literal, $pkg:literal, $ty:literal) => {{
                let mut s = node
                    .create_server(
                        mapping,
                        &Name::new(NAMESPACE, $base).map_err(|e| anyhow!("{e:?}"))?,
                        &ServiceTypeName::new($pkg, $ty),
                        sq.clone(),
                        sq.clone(),
                    )
                    .map_err(|e| {
                        anyhow!("{e:?}").context(concat!("creating the ", $base, " service"))
                    })?;
                poll.registry()
                    .register(&mut s, next_token(), Interest::READABLE)?;
                s
            }};
        }
        let services = Services {
            save: server!("save_map", "voxmap_msgs", "SaveMap"),
            load: server!("load_map", "voxmap_msgs", "LoadMap"),
            reset: server!("reset_map", "std_srvs", "Trigger"),
            raytrace: server!("raytrace", "voxmap_msgs", "Raytrace"),
        };

        let sync = CloudSync::new(SyncConfig {
            map_frame: cfg.map_frame.clone(),
            wait_ns: (cfg.tf_timeout_ms * 1e6) as i64,
            ..SyncConfig::default()
        });
        let frames = FramePublisher::connect(prefix, map).context("opening the frame port")?;
        let snapshots =
            SnapshotSubscriber::connect(prefix, map).context("opening the snapshot port")?;
        let control = MapControl::connect(prefix, map).context("opening the control port")?;
        eprintln!(
            "voxmap serve: ros2: node /{} ({}); clouds from {}; map frame '{}'; outputs on {NAMESPACE}/occupied, {NAMESPACE}/octomap_binary, {NAMESPACE}/grid every {} ms",
            cfg.node_name,
            discovery.describe(),
            if cfg.cloud_topics.is_empty() {
                "no topic".to_string()
            } else {
                cfg.cloud_topics.iter().map(|t| t.topic.as_str()).collect::<Vec<_>>().join(", ")
            },
            cfg.map_frame,
            cfg.publish_period_ms,
        );
        Ok(Self {
            cfg,
            counters,
            poll,
            clouds,
            tf,
            tf_static,
            outputs,
            services,
            sync,
            frames,
            snapshots,
            control,
            output_names,
            last_output: [None; 3],
            last_output_at: None,
            drops_logged: 0,
            participant,
            _node: node,
        })
    }

    fn run(&mut self, stop: &AtomicBool) -> Result<()> {
        let mut events = Events::with_capacity(64);
        let period = Duration::from_secs_f64(self.cfg.publish_period_ms / 1e3);
        while !stop.load(Relaxed) {
            // Wake for DDS data, for the next output, and often enough to see `stop` and
            // to time out clouds that wait for a transform.
            // Once an output is due, a new snapshot is looked for at each wake-up.
            let tick = Duration::from_millis(20);
            let timeout = match self
                .last_output_at
                .map(|t| period.saturating_sub(t.elapsed()))
            {
                Some(left) if !left.is_zero() => left.min(tick),
                _ => tick,
            };
            if let Err(e) = self.poll.poll(&mut events, Some(timeout)) {
                if e.kind() != std::io::ErrorKind::Interrupted {
                    return Err(anyhow!(e).context("waiting for ROS 2 data"));
                }
            }
            self.take_transforms();
            self.take_clouds();
            self.sync.advance(now_ns());
            for r in self.sync.ready() {
                self.posed(r);
            }
            if self.last_output_at.is_none_or(|t| t.elapsed() >= period) {
                self.publish_outputs();
            }
            self.answer_services();
        }
        Ok(())
    }

    fn take_transforms(&mut self) {
        for (sub, is_static) in [(&self.tf, false), (&self.tf_static, true)] {
            loop {
                match sub.take() {
                    Ok(Some((m, _))) => {
                        let bad = self.sync.tf_transforms(now_ns(), &m, is_static);
                        self.counters
                            .tf_rejected
                            .fetch_add(bad.len() as u64, Relaxed);
                    }
                    Ok(None) => break,
                    Err(_) => {
                        self.counters.tf_rejected.fetch_add(1, Relaxed);
                    }
                }
            }
        }
    }

    fn take_clouds(&mut self) {
        for c in &mut self.clouds {
            loop {
                let index = c.taken;
                match c.sub.take() {
                    Ok(Some((m, _))) => {
                        self.counters.clouds_received.fetch_add(1, Relaxed);
                        let m = m.map_data(ByteBuf::into_vec);
                        self.sync.decoded_cloud(&c.topic, index, now_ns(), m);
                    }
                    Ok(None) => break,
                    Err(e) => {
                        self.counters.clouds_received.fetch_add(1, Relaxed);
                        self.counters.clouds_malformed.fetch_add(1, Relaxed);
                        let what = format!("{} cloud {index}: {e}", c.topic);
                        log_drop(&mut self.drops_logged, &what);
                    }
                }
                c.taken += 1;
            }
        }
    }

    /// A cloud whose wait is over: sent to the service, or counted by why not.
    fn posed(&mut self, r: Result<PosedCloud, voxmap_ros::sync::Dropped>) {
        let c = match r {
            Ok(c) => c,
            Err(d) => {
                let counter = match d.reason {
                    DropReason::Transform(_) => &self.counters.clouds_no_tf,
                    DropReason::Decode(_) | DropReason::Cloud(_) => &self.counters.clouds_malformed,
                };
                counter.fetch_add(1, Relaxed);
                log_drop(&mut self.drops_logged, &d.to_string());
                return;
            }
        };
        let range = self
            .clouds
            .iter()
            .find(|i| i.topic == c.topic)
            .and_then(|i| i.max_range);
        let mut points = c.points.points;
        if let Some(r) = range {
            let r2 = (r * r) as f32;
            points.retain(|p| p[0] * p[0] + p[1] * p[1] + p[2] * p[2] <= r2);
        }
        let stamp = c.stamp.ns().max(0) as u64;
        match self.frames.publish(&c.pose, stamp, &points) {
            Ok(_) => {
                self.counters.clouds_sent.fetch_add(1, Relaxed);
            }
            Err(e) => {
                self.counters.clouds_not_sent.fetch_add(1, Relaxed);
                log_drop(
                    &mut self.drops_logged,
                    &format!(
                        "{} cloud {}: not sent to the service: {}",
                        c.topic,
                        c.index,
                        error_chain(&e)
                    ),
                );
            }
        }
    }

    /// The newest snapshot on each map topic that has a subscriber and has not had it yet
    /// (a topic nobody reads costs nothing; one that gains a reader gets the current map
    /// within a period, and keeps it latched for later ones).
    fn publish_outputs(&mut self) {
        let frame = self.cfg.map_frame.clone();
        let (zmin, zmax) = (self.cfg.grid_z_min, self.cfg.grid_z_max);
        // Receive first, then compare the sample's header with what each topic has.
        match self.snapshots.latest() {
            Ok(Some(_)) => {}
            Ok(None) => return,
            Err(e) => {
                self.counters.output_failures.fetch_add(1, Relaxed);
                eprintln!(
                    "voxmap serve: ros2: no snapshot to publish: {}",
                    error_chain(&e)
                );
                self.last_output_at = Some(Instant::now());
                return;
            }
        }
        let Some(published) = self.snapshots.wire_header().map(|h| h.published_ns) else {
            return;
        };
        let readers: Vec<String> = self
            .participant
            .discovered_readers()
            .into_iter()
            .map(|r| r.subscription_topic_data.topic_name().clone())
            .collect();
        let due: Vec<bool> = self
            .output_names
            .iter()
            .zip(&self.last_output)
            .map(|(t, last)| *last != Some(published) && readers.iter().any(|r| r == t))
            .collect();
        if !due.contains(&true) {
            return;
        }
        let Ok(Some(view)) = self.snapshots.latest() else {
            return;
        };
        let started = Instant::now();
        let out = &self.outputs;
        let results = [
            due[0].then(|| {
                out.occupied
                    .publish(outputs::occupied_cloud(&view, &frame))
                    .map_err(write_error)
            }),
            due[1].then(|| {
                let m = outputs::octomap(&view, &frame).context("encoding the octomap")?;
                out.octomap.publish(m).map_err(write_error)
            }),
            due[2].then(|| {
                let m = outputs::grid(&view, &frame, zmin, zmax).context("projecting the grid")?;
                out.grid.publish(m).map_err(write_error)
            }),
        ];
        self.last_output_at = Some(Instant::now());
        self.counters
            .last_output_us
            .store(started.elapsed().as_micros() as u64, Relaxed);
        for (i, r) in results.into_iter().enumerate() {
            match r {
                None => {}
                Some(Ok(())) => {
                    self.last_output[i] = Some(published);
                    self.counters.outputs_published.fetch_add(1, Relaxed);
                }
                Some(Err(e)) => {
                    // Marked as done: a map that cannot be encoded is not retried each tick.
                    self.last_output[i] = Some(published);
                    self.counters.output_failures.fetch_add(1, Relaxed);
                    eprintln!(
                        "voxmap serve: ros2: {} not published: {e:#}",
                        self.output_names[i]
                    );
                }
            }
        }
    }

    fn answer_services(&mut self) {
        let counters = self.counters.clone();
        let calls = &counters.service_calls;
        let outcome = |r: Result<(), voxmap_client::ClientError>, done: String| match r {
            Ok(()) => Outcome {
                success: true,
                message: done,
            },
            Err(e) => Outcome {
                success: false,
                message: error_chain(&e),
            },
        };
        while let Ok(Some((id, req))) = self.services.save.receive_request() {
            calls.fetch_add(1, Relaxed);
            let o = outcome(
                self.control.save(&req.path),
                format!("saved to {}", req.path),
            );
            let _ = self.services.save.send_response(id, o);
        }
        while let Ok(Some((id, req))) = self.services.load.receive_request() {
            calls.fetch_add(1, Relaxed);
            let o = outcome(self.control.load(&req.path), format!("loaded {}", req.path));
            let _ = self.services.load.send_response(id, o);
        }
        while let Ok(Some((id, _))) = self.services.reset.receive_request() {
            calls.fetch_add(1, Relaxed);
            let o = outcome(self.control.clear(), "map cleared".into());
            let _ = self.services.reset.send_response(id, o);
        }
        while let Ok(Some((id, req))) = self.services.raytrace.receive_request() {
            calls.fetch_add(1, Relaxed);
            let r = self.raytrace(&req);
            let _ = self.services.raytrace.send_response(id, r);
        }
    }

    fn raytrace(&mut self, req: &RaytraceRequest) -> RaytraceResponse {
        let fail = |message: String| RaytraceResponse {
            success: false,
            hit: false,
            end_point: req.origin,
            message,
        };
        let (o, d) = (req.origin, req.direction);
        let norm = (d.x * d.x + d.y * d.y + d.z * d.z).sqrt();
        let finite = [o.x, o.y, o.z, d.x, d.y, d.z, req.max_length]
            .iter()
            .all(|v| v.is_finite());
        if !finite || norm == 0.0 || req.max_length < 0.0 {
            return fail("origin, direction and max_length must be finite, the direction non-zero and max_length >= 0".into());
        }
        let s = req.max_length / norm;
        let from = WorldPoint::new(o.x, o.y, o.z);
        let to = WorldPoint::new(o.x + d.x * s, o.y + d.y * s, o.z + d.z * s);
        let view = match self.snapshots.latest() {
            Ok(Some(v)) => v,
            Ok(None) => return fail("no snapshot published yet".into()),
            Err(e) => return fail(error_chain(&e)),
        };
        match view.first_hit(&from, &to, false) {
            Ok(Some(v)) => {
                let c = view.transform().voxel_center(v);
                RaytraceResponse {
                    success: true,
                    hit: true,
                    end_point: Vector3 {
                        x: c.x,
                        y: c.y,
                        z: c.z,
                    },
                    message: String::new(),
                }
            }
            Ok(None) => RaytraceResponse {
                success: true,
                hit: false,
                end_point: Vector3 {
                    x: to.x,
                    y: to.y,
                    z: to.z,
                },
                message: String::new(),
            },
            Err(e) => fail(e.to_string()),
        }
    }
}

/// A DDS write error without the message it carries (which may be megabytes).
fn write_error<D>(e: ros2_client::WriteError<D>) -> anyhow::Error {
    anyhow!("{e}")
}

/// Log the first drops one by one, then every 100th, so a missing transform does not
/// flood the log (the counters have them all).
fn log_drop(logged: &mut u64, what: &str) {
    *logged += 1;
    if *logged <= 5 || (*logged).is_multiple_of(100) {
        eprintln!("voxmap serve: ros2: dropped #{logged}: {what}");
    }
}

/// A ROS 2 reader of the three map topics that counts what it receives: what a remote
/// RViz costs the service, for `voxmap bench --e2e --e2e-ros2`.
pub struct MapTopicsReader {
    _node: Node,
    subs: (
        Subscription<PointCloud2<ByteBuf>>,
        Subscription<Octomap>,
        Subscription<OccupancyGrid>,
    ),
    /// Messages and bytes of `data` received so far.
    pub messages: u64,
    pub bytes: u64,
}

impl MapTopicsReader {
    pub fn new(discovery: &Discovery) -> Result<Self> {
        let (mut node, _) = new_node(discovery, "voxmap_bench_reader")?;
        let [a, b, c] = map_topics(&node)?;
        let e = |e| anyhow!("{e:?}");
        let subs = (
            node.create_subscription(&a, None).map_err(e)?,
            node.create_subscription(&b, None).map_err(e)?,
            node.create_subscription(&c, None).map_err(e)?,
        );
        Ok(Self {
            _node: node,
            subs,
            messages: 0,
            bytes: 0,
        })
    }

    /// Take what has arrived.
    pub fn take(&mut self) {
        while let Ok(Some((m, _))) = self.subs.0.take() {
            self.messages += 1;
            self.bytes += m.data.len() as u64;
        }
        while let Ok(Some((m, _))) = self.subs.1.take() {
            self.messages += 1;
            self.bytes += m.data.len() as u64;
        }
        while let Ok(Some((m, _))) = self.subs.2.take() {
            self.messages += 1;
            self.bytes += m.data.len() as u64;
        }
    }
}

//! voxmap-client: what sensor drivers and planners link to talk to a running
//! `voxmap serve` over iceoryx2 shared memory.
//!
//! - [`FramePublisher`]: loan a shared-memory slice for `n` points, fill it in place,
//!   send. No copy.
//! - [`SnapshotSubscriber`]: [`SnapshotSubscriber::latest`] gives a
//!   [`SnapshotView`] over the shared-memory sample itself: no copy, no deserialization;
//!   [`SnapshotSubscriber::wait_for_update`] blocks on an event, not a busy loop.
//!   Many point checks at once (a trajectory's samples) go through
//!   [`SnapshotView::states_at`], which overlaps their memory reads.
//!
//! ```no_run
//! use voxmap_client::{SnapshotSubscriber, VoxelState, WorldPoint};
//! let mut sub = SnapshotSubscriber::connect("voxmap", "default")?;
//! sub.wait_for_update(std::time::Duration::from_secs(1))?;
//! if let Some(view) = sub.latest()? {
//!     let clear = view.first_hit(&WorldPoint::new(0.0, 0.0, 0.0), &WorldPoint::new(5.0, 0.0, 0.0), true);
//!     println!("seq {}: line of sight {:?}", view.sequence(), clear);
//! }
//! # Ok::<(), voxmap_client::ClientError>(())
//! ```

use iceoryx2::port::listener::Listener;
use iceoryx2::port::notifier::Notifier;
use iceoryx2::port::publisher::Publisher;
use iceoryx2::port::subscriber::Subscriber;
use iceoryx2::prelude::*;
use iceoryx2::sample::Sample;
use iceoryx2::sample_mut::SampleMut;
use std::time::Duration;

pub use nalgebra::Isometry3;
pub use voxmap_core::snapshot::{InvalidSegment, SnapshotError, SnapshotView};
pub use voxmap_core::wire::{
    ControlKind, ControlRequest, ControlResponse, FrameHeader, ServiceNames, StatsWire,
};
pub use voxmap_core::{VoxelCoord, VoxelState, WorldPoint};

/// Something went wrong talking to iceoryx2 or reading a snapshot.
#[derive(Debug)]
#[non_exhaustive]
pub enum ClientError {
    /// Creating the node, a service or a port failed (the text says which and why).
    Connect(String),
    /// Loaning or sending a sample failed.
    Send(String),
    /// Receiving failed.
    Receive(String),
    /// The received snapshot did not validate.
    Snapshot(SnapshotError),
    /// The service answered a control request with an error.
    Rejected(String),
}

impl std::fmt::Display for ClientError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Connect(s) => write!(f, "connect: {s}"),
            Self::Send(s) => write!(f, "send: {s}"),
            Self::Receive(s) => write!(f, "receive: {s}"),
            Self::Snapshot(e) => write!(f, "snapshot: {e}"),
            Self::Rejected(m) => write!(f, "rejected by the service: {m}"),
        }
    }
}

impl std::error::Error for ClientError {}

fn connect_err(what: &str) -> impl Fn(&dyn std::fmt::Debug) -> ClientError + '_ {
    move |e| ClientError::Connect(format!("{what}: {e:?}"))
}

/// Service-level settings both sides must agree on (when creating; minimums when opening).
pub mod qos {
    pub const FRAME_SUBSCRIBER_BUFFER: usize = 4;
    pub const MAX_FRAME_PUBLISHERS: usize = 16;
    pub const MAX_SNAPSHOT_SUBSCRIBERS: usize = 16;
    pub const SNAPSHOT_BORROWED: usize = 2;
    pub const MAX_NODES: usize = 64;
}

pub(crate) fn node(name: &str) -> Result<Node<ipc::Service>, ClientError> {
    let name = NodeName::new(name).map_err(|e| connect_err("node name")(&e))?;
    NodeBuilder::new()
        .name(&name)
        .config(&Config::default())
        .signal_handling_mode(SignalHandlingMode::Disabled)
        .create::<ipc::Service>()
        .map_err(|e| connect_err("node")(&e))
}

fn service_name(s: &str) -> Result<ServiceName, ClientError> {
    s.try_into().map_err(|e| connect_err("service name")(&e))
}

/// The frames service (shared by publishers and the service).
pub fn open_frames(
    node: &Node<ipc::Service>,
    names: &ServiceNames,
) -> Result<
    iceoryx2::service::port_factory::publish_subscribe::PortFactory<
        ipc::Service,
        [[f32; 3]],
        FrameHeader,
    >,
    ClientError,
> {
    node.service_builder(&service_name(&names.frames)?)
        .publish_subscribe::<[[f32; 3]]>()
        .user_header::<FrameHeader>()
        .subscriber_max_buffer_size(qos::FRAME_SUBSCRIBER_BUFFER)
        .history_size(0)
        .max_publishers(qos::MAX_FRAME_PUBLISHERS)
        .max_nodes(qos::MAX_NODES)
        .enable_safe_overflow(true)
        .open_or_create()
        .map_err(|e| connect_err("frames service")(&e))
}

/// The snapshot service.
pub fn open_snapshots(
    node: &Node<ipc::Service>,
    names: &ServiceNames,
) -> Result<
    iceoryx2::service::port_factory::publish_subscribe::PortFactory<
        ipc::Service,
        [u8],
        voxmap_core::wire::SnapshotHeader,
    >,
    ClientError,
> {
    node.service_builder(&service_name(&names.snapshot)?)
        .publish_subscribe::<[u8]>()
        .user_header::<voxmap_core::wire::SnapshotHeader>()
        .history_size(1)
        .subscriber_max_buffer_size(2)
        .subscriber_max_borrowed_samples(qos::SNAPSHOT_BORROWED)
        .max_subscribers(qos::MAX_SNAPSHOT_SUBSCRIBERS)
        .max_publishers(1)
        .max_nodes(qos::MAX_NODES)
        .enable_safe_overflow(true)
        .open_or_create()
        .map_err(|e| connect_err("snapshot service")(&e))
}

/// An event service by name.
pub fn open_event(
    node: &Node<ipc::Service>,
    name: &str,
) -> Result<iceoryx2::service::port_factory::event::PortFactory<ipc::Service>, ClientError> {
    node.service_builder(&service_name(name)?)
        .event()
        .max_nodes(qos::MAX_NODES)
        .open_or_create()
        .map_err(|e| connect_err("event service")(&e))
}

/// The control service.
pub fn open_control(
    node: &Node<ipc::Service>,
    names: &ServiceNames,
) -> Result<
    iceoryx2::service::port_factory::request_response::PortFactory<
        ipc::Service,
        ControlRequest,
        (),
        ControlResponse,
        (),
    >,
    ClientError,
> {
    node.service_builder(&service_name(&names.control)?)
        .request_response::<ControlRequest, ControlResponse>()
        .max_nodes(qos::MAX_NODES)
        .open_or_create()
        .map_err(|e| connect_err("control service")(&e))
}

/// Where snapshots cover the map.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum SnapshotScope {
    Whole,
    /// A box of these half extents (metres) around the latest sensor pose.
    AroundSensor {
        half_extents: [f64; 3],
    },
    /// A fixed box in the map frame.
    Fixed {
        min: [f64; 3],
        max: [f64; 3],
    },
}

/// Requests to a running service: stats, save, load, clear, snapshot scope.
pub struct MapControl {
    client: iceoryx2::port::client::Client<ipc::Service, ControlRequest, (), ControlResponse, ()>,
    wake: Notifier<ipc::Service>,
    timeout: Duration,
    _node: Node<ipc::Service>,
}

impl MapControl {
    pub fn connect(prefix: &str, map: &str) -> Result<Self, ClientError> {
        let names = ServiceNames::new(prefix, map);
        let node = node("voxmap-control")?;
        let client = open_control(&node, &names)?
            .client_builder()
            .create()
            .map_err(|e| connect_err("control client")(&e))?;
        // Requests are served when the service wakes; frames and requests share its wake-up.
        let wake = open_event(&node, &names.frames_event)?
            .notifier_builder()
            .create()
            .map_err(|e| connect_err("control notifier")(&e))?;
        Ok(Self {
            client,
            wake,
            timeout: Duration::from_secs(30),
            _node: node,
        })
    }

    /// How long to wait for each response (default 30 s: `load` and `save` do file I/O).
    pub fn set_timeout(&mut self, t: Duration) {
        self.timeout = t;
    }

    /// Send a raw request and wait for the answer.
    pub fn request(&self, req: ControlRequest) -> Result<ControlResponse, ClientError> {
        let pending = self
            .client
            .send_copy(req)
            .map_err(|e| ClientError::Send(format!("control request: {e:?}")))?;
        self.wake
            .notify()
            .map_err(|e| ClientError::Send(format!("notify: {e:?}")))?;
        let deadline = std::time::Instant::now() + self.timeout;
        loop {
            if let Some(r) = pending
                .receive()
                .map_err(|e| ClientError::Receive(format!("{e:?}")))?
            {
                return Ok(*r.payload());
            }
            if std::time::Instant::now() > deadline {
                return Err(ClientError::Receive(
                    "no control response before the timeout (is the service running?)".into(),
                ));
            }
            std::thread::sleep(Duration::from_millis(1));
        }
    }

    fn checked(&self, req: ControlRequest) -> Result<ControlResponse, ClientError> {
        let r = self.request(req)?;
        if r.ok == 1 {
            Ok(r)
        } else {
            Err(ClientError::Rejected(r.message().to_string()))
        }
    }

    pub fn stats(&self) -> Result<StatsWire, ClientError> {
        Ok(self.checked(ControlRequest::new(ControlKind::Stats))?.stats)
    }

    /// Save the map to `path` on the service's machine.
    pub fn save(&self, path: &str) -> Result<(), ClientError> {
        let req = ControlRequest::with_path(ControlKind::Save, path)
            .ok_or(ClientError::Rejected("path too long".into()))?;
        self.checked(req).map(|_| ())
    }

    /// Replace the service's map with the file at `path`.
    pub fn load(&self, path: &str) -> Result<(), ClientError> {
        let req = ControlRequest::with_path(ControlKind::Load, path)
            .ok_or(ClientError::Rejected("path too long".into()))?;
        self.checked(req).map(|_| ())
    }

    pub fn clear(&self) -> Result<(), ClientError> {
        self.checked(ControlRequest::new(ControlKind::Clear))
            .map(|_| ())
    }

    pub fn set_scope(&self, scope: SnapshotScope) -> Result<(), ClientError> {
        let mut r = ControlRequest::new(ControlKind::SetScope);
        match scope {
            SnapshotScope::Whole => {}
            SnapshotScope::AroundSensor { half_extents } => {
                r.scope_kind = 1;
                r.scope[..3].copy_from_slice(&half_extents);
            }
            SnapshotScope::Fixed { min, max } => {
                r.scope_kind = 2;
                r.scope[..3].copy_from_slice(&min);
                r.scope[3..].copy_from_slice(&max);
            }
        }
        self.checked(r).map(|_| ())
    }
}

/// Publishes point-cloud frames to a map.
///
/// ```no_run
/// use voxmap_client::{FramePublisher, Isometry3};
/// let mut pubr = FramePublisher::connect("voxmap", "default")?;
/// let mut frame = pubr.loan(3)?;
/// frame.points_mut().copy_from_slice(&[[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]);
/// frame.send(&Isometry3::identity(), 0)?;
/// # Ok::<(), voxmap_client::ClientError>(())
/// ```
pub struct FramePublisher {
    publisher: Publisher<ipc::Service, [[f32; 3]], FrameHeader>,
    notifier: Notifier<ipc::Service>,
    sequence: u64,
    _node: Node<ipc::Service>,
}

/// A loaned frame in shared memory: fill [`FrameLoan::points_mut`], then send.
pub struct FrameLoan<'p> {
    sample: SampleMut<ipc::Service, [[f32; 3]], FrameHeader>,
    owner: &'p mut FramePublisher,
}

impl FramePublisher {
    /// Connect to map `map` under service prefix `prefix` (e.g. "voxmap", "default").
    pub fn connect(prefix: &str, map: &str) -> Result<Self, ClientError> {
        let names = ServiceNames::new(prefix, map);
        let node = node("voxmap-frame-publisher")?;
        let publisher = open_frames(&node, &names)?
            .publisher_builder()
            .initial_max_slice_len(65536)
            .allocation_strategy(AllocationStrategy::PowerOfTwo)
            .create()
            .map_err(|e| connect_err("frame publisher")(&e))?;
        let notifier = open_event(&node, &names.frames_event)?
            .notifier_builder()
            .create()
            .map_err(|e| connect_err("frame notifier")(&e))?;
        Ok(Self {
            publisher,
            notifier,
            // Sequences start at 1: a snapshot with sequence 0 holds no frame yet.
            sequence: 1,
            _node: node,
        })
    }

    /// Loan shared memory for `n` points (zeroed).
    pub fn loan(&mut self, n: usize) -> Result<FrameLoan<'_>, ClientError> {
        let sample = self
            .publisher
            .loan_slice(n)
            .map_err(|e| ClientError::Send(format!("loan {n} points: {e:?}")))?;
        Ok(FrameLoan {
            sample,
            owner: self,
        })
    }

    /// Copy `points` into a loan and send it (for callers that already hold a buffer).
    pub fn publish(
        &mut self,
        pose: &Isometry3<f64>,
        timestamp_ns: u64,
        points: &[[f32; 3]],
    ) -> Result<u64, ClientError> {
        let mut l = self.loan(points.len())?;
        l.points_mut().copy_from_slice(points);
        l.send(pose, timestamp_ns)
    }
}

impl FrameLoan<'_> {
    /// The points, in the sensor frame, in shared memory.
    pub fn points_mut(&mut self) -> &mut [[f32; 3]] {
        self.sample.payload_mut()
    }

    /// Stamp the header and send; returns the frame's sequence number.
    pub fn send(mut self, pose: &Isometry3<f64>, timestamp_ns: u64) -> Result<u64, ClientError> {
        let seq = self.owner.sequence;
        let n = self.sample.payload().len() as u64;
        *self.sample.user_header_mut() = FrameHeader {
            sequence: seq,
            timestamp_ns,
            point_count: n,
            ..FrameHeader::with_pose(pose)
        };
        self.send_raw()
    }

    /// Send with the header as already written by [`Self::header_mut`] (for tests of bad input).
    pub fn send_raw(self) -> Result<u64, ClientError> {
        let seq = self.sample.user_header().sequence;
        self.sample
            .send()
            .map_err(|e| ClientError::Send(format!("{e:?}")))?;
        self.owner.sequence += 1;
        self.owner
            .notifier
            .notify()
            .map_err(|e| ClientError::Send(format!("notify: {e:?}")))?;
        Ok(seq)
    }

    /// The header, to be written by hand before [`Self::send_raw`].
    pub fn header_mut(&mut self) -> &mut FrameHeader {
        self.sample.user_header_mut()
    }
}

/// Receives snapshots of a map; holds the newest sample and lends views into it.
pub struct SnapshotSubscriber {
    subscriber: Subscriber<ipc::Service, [u8], voxmap_core::wire::SnapshotHeader>,
    listener: Listener<ipc::Service>,
    current: Option<Sample<ipc::Service, [u8], voxmap_core::wire::SnapshotHeader>>,
    _node: Node<ipc::Service>,
}

impl SnapshotSubscriber {
    pub fn connect(prefix: &str, map: &str) -> Result<Self, ClientError> {
        let names = ServiceNames::new(prefix, map);
        let node = node("voxmap-planner")?;
        let subscriber = open_snapshots(&node, &names)?
            .subscriber_builder()
            .create()
            .map_err(|e| connect_err("snapshot subscriber")(&e))?;
        let listener = open_event(&node, &names.snapshot_event)?
            .listener_builder()
            .create()
            .map_err(|e| connect_err("snapshot listener")(&e))?;
        Ok(Self {
            subscriber,
            listener,
            current: None,
            _node: node,
        })
    }

    /// Take any newer snapshot; true if one arrived.
    fn poll(&mut self) -> Result<bool, ClientError> {
        let mut got = false;
        while let Some(s) = self
            .subscriber
            .receive()
            .map_err(|e| ClientError::Receive(format!("{e:?}")))?
        {
            self.current = Some(s); // drops (returns) the older sample
            got = true;
        }
        Ok(got)
    }

    /// Wait up to `timeout` for a snapshot newer than the one held; true if one arrived.
    pub fn wait_for_update(&mut self, timeout: Duration) -> Result<bool, ClientError> {
        if self.poll()? {
            return Ok(true);
        }
        let deadline = std::time::Instant::now() + timeout;
        loop {
            let left = deadline.saturating_duration_since(std::time::Instant::now());
            self.listener
                .timed_wait(|_| {}, left.max(Duration::from_millis(1)))
                .map_err(|e| ClientError::Receive(format!("{e:?}")))?;
            if self.poll()? {
                return Ok(true);
            }
            if left.is_zero() {
                return Ok(false);
            }
        }
    }

    /// The newest snapshot, read in place in shared memory.
    pub fn latest(&mut self) -> Result<Option<SnapshotView<'_>>, ClientError> {
        self.poll()?;
        let Some(s) = &self.current else {
            return Ok(None);
        };
        let len = (s.user_header().len as usize).min(s.payload().len());
        SnapshotView::open(&s.payload()[..len])
            .map(Some)
            .map_err(ClientError::Snapshot)
    }

    /// The wire header of the held sample (sequence, length, when it was published).
    pub fn wire_header(&self) -> Option<voxmap_core::wire::SnapshotHeader> {
        self.current.as_ref().map(|s| *s.user_header())
    }

    /// The whole shared-memory payload of the held sample (to check it is not a copy).
    pub fn sample_bytes(&self) -> Option<&[u8]> {
        self.current.as_ref().map(|s| s.payload())
    }
}

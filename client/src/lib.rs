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

use iceoryx2::port::client::RequestSendError;
use iceoryx2::port::listener::{Listener, ListenerCreateError, ListenerWaitError};
use iceoryx2::port::notifier::{Notifier, NotifierCreateError, NotifierNotifyError};
use iceoryx2::port::publisher::{Publisher, PublisherCreateError};
use iceoryx2::port::subscriber::{Subscriber, SubscriberCreateError};
use iceoryx2::port::{LoanError, ReceiveError, SendError};
use iceoryx2::prelude::*;
use iceoryx2::sample::Sample;
use iceoryx2::sample_mut::SampleMut;
use iceoryx2::service::port_factory::client::ClientCreateError;
use std::time::Duration;
use voxmap_ipc::ports::{open_control, open_event, open_frames, open_snapshots};

pub use nalgebra::Isometry3;
pub use voxmap_core::snapshot::{InvalidBox, InvalidSegment, SnapshotError, SnapshotView};
pub use voxmap_core::{VoxelCoord, VoxelState, WorldPoint};
pub use voxmap_ipc::{
    ControlError, ControlKind, ControlRequest, ControlResponse, FrameHeader, MapScope, OpenError,
    ServiceNames, SnapshotHeader, StatsWire,
};

/// Something went wrong talking to the service or reading a snapshot. The cause (iceoryx2's
/// own error, the snapshot's or the request's) is the [`std::error::Error::source`], not
/// repeated in the message.
#[derive(Debug)]
#[non_exhaustive]
pub enum ClientError {
    /// Opening the node or a service failed.
    Connect(OpenError),
    /// Creating the frame publisher failed.
    Publisher(PublisherCreateError),
    /// Creating the snapshot subscriber failed.
    Subscriber(SubscriberCreateError),
    /// Creating a wake-up notifier failed.
    Notifier(NotifierCreateError),
    /// Creating the snapshot wake-up listener failed.
    Listener(ListenerCreateError),
    /// Creating the control client failed.
    ControlClient(ClientCreateError),
    /// Loaning shared memory for `points` points failed.
    Loan { points: usize, source: LoanError },
    /// Sending a sample failed.
    Send(SendError),
    /// Waking the other side failed.
    Notify(NotifierNotifyError),
    /// Sending a control request failed.
    Request(RequestSendError),
    /// Receiving a sample or a response failed.
    Receive(ReceiveError),
    /// Waiting for a wake-up failed.
    Wait(ListenerWaitError),
    /// No control response came within this timeout (is the service running?).
    Timeout(Duration),
    /// The request could not be built (a path too long).
    BadRequest(ControlError),
    /// The received snapshot did not validate.
    Snapshot(SnapshotError),
    /// The service answered a control request with an error.
    Rejected(String),
}

impl std::fmt::Display for ClientError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Connect(_) => write!(f, "connecting to the service failed"),
            Self::Publisher(_) => write!(f, "creating the frame publisher failed"),
            Self::Subscriber(_) => write!(f, "creating the snapshot subscriber failed"),
            Self::Notifier(_) => write!(f, "creating a wake-up notifier failed"),
            Self::Listener(_) => write!(f, "creating the snapshot listener failed"),
            Self::ControlClient(_) => write!(f, "creating the control client failed"),
            Self::Loan { points, .. } => {
                write!(f, "loaning shared memory for {points} points failed")
            }
            Self::Send(_) => write!(f, "sending a sample failed"),
            Self::Notify(_) => write!(f, "waking the other side failed"),
            Self::Request(_) => write!(f, "sending a control request failed"),
            Self::Receive(_) => write!(f, "receiving failed"),
            Self::Wait(_) => write!(f, "waiting for a wake-up failed"),
            Self::Timeout(t) => write!(
                f,
                "no control response within {:.1} s (is the service running?)",
                t.as_secs_f64()
            ),
            Self::BadRequest(_) => write!(f, "bad control request"),
            Self::Snapshot(_) => write!(f, "the snapshot did not validate"),
            Self::Rejected(m) => write!(f, "rejected by the service: {m}"),
        }
    }
}

impl std::error::Error for ClientError {
    fn source(&self) -> Option<&(dyn std::error::Error + 'static)> {
        match self {
            Self::Connect(e) => Some(e),
            Self::Publisher(e) => Some(e),
            Self::Subscriber(e) => Some(e),
            Self::Notifier(e) => Some(e),
            Self::Listener(e) => Some(e),
            Self::ControlClient(e) => Some(e),
            Self::Loan { source, .. } => Some(source),
            Self::Send(e) => Some(e),
            Self::Notify(e) => Some(e),
            Self::Request(e) => Some(e),
            Self::Receive(e) => Some(e),
            Self::Wait(e) => Some(e),
            Self::BadRequest(e) => Some(e),
            Self::Snapshot(e) => Some(e),
            Self::Timeout(_) | Self::Rejected(_) => None,
        }
    }
}

impl From<OpenError> for ClientError {
    fn from(e: OpenError) -> Self {
        Self::Connect(e)
    }
}

/// A client node: it leaves SIGINT/SIGTERM to the process.
fn node(name: &str) -> Result<Node<ipc::Service>, ClientError> {
    Ok(voxmap_ipc::ports::node(name, SignalHandlingMode::Disabled)?)
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
            .map_err(ClientError::ControlClient)?;
        // Requests are served when the service wakes; frames and requests share its wake-up.
        let wake = open_event(&node, &names.frames_event)?
            .notifier_builder()
            .create()
            .map_err(ClientError::Notifier)?;
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
        let pending = self.client.send_copy(req).map_err(ClientError::Request)?;
        self.wake.notify().map_err(ClientError::Notify)?;
        let deadline = std::time::Instant::now() + self.timeout;
        loop {
            if let Some(r) = pending.receive().map_err(ClientError::Receive)? {
                return Ok(*r.payload());
            }
            if std::time::Instant::now() > deadline {
                return Err(ClientError::Timeout(self.timeout));
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
        let req =
            ControlRequest::with_path(ControlKind::Save, path).map_err(ClientError::BadRequest)?;
        self.checked(req).map(|_| ())
    }

    /// Replace the service's map with the file at `path`.
    pub fn load(&self, path: &str) -> Result<(), ClientError> {
        let req =
            ControlRequest::with_path(ControlKind::Load, path).map_err(ClientError::BadRequest)?;
        self.checked(req).map(|_| ())
    }

    pub fn clear(&self) -> Result<(), ClientError> {
        self.checked(ControlRequest::new(ControlKind::Clear))
            .map(|_| ())
    }

    /// Set where snapshots cover the map.
    pub fn set_scope(&self, scope: MapScope) -> Result<(), ClientError> {
        self.checked(ControlRequest::with_scope(scope)).map(|_| ())
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
            .map_err(ClientError::Publisher)?;
        let notifier = open_event(&node, &names.frames_event)?
            .notifier_builder()
            .create()
            .map_err(ClientError::Notifier)?;
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
            .map_err(|source| ClientError::Loan { points: n, source })?;
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
        self.sample.send().map_err(ClientError::Send)?;
        self.owner.sequence += 1;
        self.owner.notifier.notify().map_err(ClientError::Notify)?;
        Ok(seq)
    }

    /// The header, to be written by hand before [`Self::send_raw`].
    pub fn header_mut(&mut self) -> &mut FrameHeader {
        self.sample.user_header_mut()
    }
}

/// How often a waiting subscriber looks for a history sample (see `wait_for_update`).
const HISTORY_POLL: Duration = Duration::from_millis(50);

/// Receives snapshots of a map; holds the newest sample and lends views into it.
pub struct SnapshotSubscriber {
    subscriber: Subscriber<ipc::Service, [u8], SnapshotHeader>,
    listener: Listener<ipc::Service>,
    current: Option<Sample<ipc::Service, [u8], SnapshotHeader>>,
    _node: Node<ipc::Service>,
}

impl SnapshotSubscriber {
    pub fn connect(prefix: &str, map: &str) -> Result<Self, ClientError> {
        let names = ServiceNames::new(prefix, map);
        let node = node("voxmap-planner")?;
        let subscriber = open_snapshots(&node, &names)?
            .subscriber_builder()
            .create()
            .map_err(ClientError::Subscriber)?;
        let listener = open_event(&node, &names.snapshot_event)?
            .listener_builder()
            .create()
            .map_err(ClientError::Listener)?;
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
        while let Some(s) = self.subscriber.receive().map_err(ClientError::Receive)? {
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
            // The current snapshot reaches a new subscriber as history, which comes with no
            // wake-up: look again at least this often so that it is seen without waiting
            // for the next snapshot.
            let slice = left.min(HISTORY_POLL).max(Duration::from_millis(1));
            self.listener
                .timed_wait(|_| {}, slice)
                .map_err(ClientError::Wait)?;
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
    pub fn wire_header(&self) -> Option<SnapshotHeader> {
        self.current.as_ref().map(|s| *s.user_header())
    }

    /// The whole shared-memory payload of the held sample (to check it is not a copy).
    pub fn sample_bytes(&self) -> Option<&[u8]> {
        self.current.as_ref().map(|s| s.payload())
    }
}

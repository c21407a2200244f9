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
pub use voxmap_ipc::{
    ControlError, ControlKind, ControlRequest, ControlResponse, FrameHeader, FrameRejected,
    MapScope, OpenError, ServiceNames, SnapshotHeader, StatsWire, FRAME_VERSION, MAX_FRAME_POINTS,
};
pub use voxmap_reader::field::UnknownPolicy;
pub use voxmap_reader::snapshot::{
    FieldView, InvalidBox, InvalidSegment, Nearest, SnapshotError, SnapshotView,
};
pub use voxmap_reader::{VoxelCoord, VoxelState, WorldPoint};

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

/// An error and its causes as one line, `a: b: c` (for bindings that hand C or Python a
/// message rather than the error).
pub fn error_chain(e: &dyn std::error::Error) -> String {
    let mut m = e.to_string();
    let mut s = e.source();
    while let Some(c) = s {
        m.push_str(": ");
        m.push_str(&c.to_string());
        s = c.source();
    }
    m
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

    /// Send a raw request and wait for the answer. A request that reached no server (the
    /// service is starting, or restarting after a crash) is sent again until one takes it
    /// or the timeout passes; one that reached the server is never sent twice.
    pub fn request(&self, req: ControlRequest) -> Result<ControlResponse, ClientError> {
        let deadline = std::time::Instant::now() + self.timeout;
        let pending = loop {
            let pending = self.client.send_copy(req).map_err(ClientError::Request)?;
            if pending.number_of_server_connections() > 0 {
                break pending;
            }
            if std::time::Instant::now() > deadline {
                return Err(ClientError::Timeout(self.timeout));
            }
            drop(pending);
            std::thread::sleep(Duration::from_millis(1));
        };
        self.wake.notify().map_err(ClientError::Notify)?;
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

    /// Replace the service's map with the map file at `path`, or with the tile store in the
    /// directory `path` (continued lazily: its tiles load as frames and windows reach them).
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

/// A frame's pose from its wire fields (translation in metres, a unit quaternion x, y, z,
/// w), checked as the service checks it, so a binding can refuse a bad pose before
/// sending it.
pub fn frame_pose(
    translation: [f64; 3],
    rotation_xyzw: [f64; 4],
) -> Result<Isometry3<f64>, voxmap_ipc::FrameRejected> {
    FrameHeader {
        translation,
        rotation_xyzw,
        ..FrameHeader::default()
    }
    .validate(0)
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
    frame: PendingFrame,
    owner: &'p mut FramePublisher,
}

/// A loaned frame that does not borrow its publisher, for callers that keep it across
/// calls (the C and Python bindings): fill it, then [`FramePublisher::send_pending`] on the
/// publisher that loaned it. Dropping it returns the memory unsent.
pub struct PendingFrame {
    sample: SampleMut<ipc::Service, [[f32; 3]], FrameHeader>,
}

impl PendingFrame {
    /// The points, in the sensor frame, in shared memory.
    pub fn points_mut(&mut self) -> &mut [[f32; 3]] {
        self.sample.payload_mut()
    }
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
        let frame = self.loan_pending(n)?;
        Ok(FrameLoan { frame, owner: self })
    }

    /// [`Self::loan`] without the borrow: send it with [`Self::send_pending`].
    pub fn loan_pending(&mut self, n: usize) -> Result<PendingFrame, ClientError> {
        let sample = self
            .publisher
            .loan_slice(n)
            .map_err(|source| ClientError::Loan { points: n, source })?;
        Ok(PendingFrame { sample })
    }

    /// Stamp a pending frame's header and send it; returns the frame's sequence number.
    pub fn send_pending(
        &mut self,
        mut frame: PendingFrame,
        pose: &Isometry3<f64>,
        timestamp_ns: u64,
    ) -> Result<u64, ClientError> {
        let n = frame.sample.payload().len() as u64;
        *frame.sample.user_header_mut() = FrameHeader {
            sequence: self.sequence,
            timestamp_ns,
            point_count: n,
            ..FrameHeader::with_pose(pose)
        };
        self.send_raw(frame)
    }

    /// Send with the header as the caller wrote it (for tests of bad input).
    fn send_raw(&mut self, frame: PendingFrame) -> Result<u64, ClientError> {
        let seq = frame.sample.user_header().sequence;
        frame.sample.send().map_err(ClientError::Send)?;
        self.sequence += 1;
        self.notifier.notify().map_err(ClientError::Notify)?;
        Ok(seq)
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
        self.frame.points_mut()
    }

    /// Stamp the header and send; returns the frame's sequence number.
    pub fn send(self, pose: &Isometry3<f64>, timestamp_ns: u64) -> Result<u64, ClientError> {
        self.owner.send_pending(self.frame, pose, timestamp_ns)
    }

    /// Send with the header as already written by [`Self::header_mut`] (for tests of bad input).
    pub fn send_raw(self) -> Result<u64, ClientError> {
        self.owner.send_raw(self.frame)
    }

    /// The header, to be written by hand before [`Self::send_raw`].
    pub fn header_mut(&mut self) -> &mut FrameHeader {
        self.frame.sample.user_header_mut()
    }
}

/// How often a waiting subscriber looks for a history sample (see `wait_for_update`).
const HISTORY_POLL: Duration = Duration::from_millis(50);

type SnapshotSample = Sample<ipc::Service, [u8], SnapshotHeader>;

/// A received snapshot sample, validated once, that can outlive the subscriber's next
/// receive: what [`SnapshotSubscriber::latest_held`] gives a caller that keeps a view across
/// calls (the C and Python bindings). It holds the shared-memory sample: a subscriber may
/// hold at most [`voxmap_ipc::ports::qos::SNAPSHOT_BORROWED`] samples at once, so held
/// snapshots of two different older samples make receives fail
/// (`ReceiveError::ExceedsMaxBorrows`) until one is dropped; one is fine. Not `Send`: iceoryx2's `ipc` samples stay on the thread
/// of their subscriber.
#[derive(Clone)]
pub struct HeldSnapshot {
    // Field order: the view, which points into the sample, is dropped first.
    view: SnapshotView<'static>,
    sample: std::rc::Rc<SnapshotSample>,
}

impl HeldSnapshot {
    fn new(sample: std::rc::Rc<SnapshotSample>) -> Result<Self, SnapshotError> {
        let payload = sample.payload();
        let len = (sample.user_header().len as usize).min(payload.len());
        // SAFETY: the bytes are the sample's payload in shared memory, which stays mapped at
        // the same address while the sample lives (an iceoryx2 `Sample` keeps its segment
        // mapped and is never written by the publisher while loaned to us). `Rc` keeps the
        // sample alive as long as this struct; the `'static` view is handed out only as a
        // `SnapshotView<'_>` borrowed from `self`, and is dropped before the sample.
        let bytes: &'static [u8] = unsafe { std::slice::from_raw_parts(payload.as_ptr(), len) };
        let view = SnapshotView::open(bytes)?;
        Ok(Self { view, sample })
    }

    /// The snapshot, read in place.
    pub fn view(&self) -> SnapshotView<'_> {
        self.view
    }

    /// The wire header (sequence, length, when it was published).
    pub fn wire_header(&self) -> SnapshotHeader {
        *self.sample.user_header()
    }
}

/// Receives snapshots of a map; holds the newest sample and lends views into it.
pub struct SnapshotSubscriber {
    subscriber: Subscriber<ipc::Service, [u8], SnapshotHeader>,
    listener: Listener<ipc::Service>,
    /// The newest sample, and what validating it gave (once per sample, not per call).
    current: Option<(
        std::rc::Rc<SnapshotSample>,
        Result<HeldSnapshot, SnapshotError>,
    )>,
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
        let mut newest = None;
        loop {
            match self.subscriber.receive() {
                Ok(Some(s)) => {
                    // Drops (returns) the older sample, unless a held snapshot keeps it.
                    self.current = None;
                    newest = Some(s);
                }
                Ok(None) => break,
                // Held snapshots use up the borrows (iceoryx2 says so only when a sample
                // is waiting): take the newer one got so far and the rest on a later call;
                // or make room by letting go of our newest, if no held snapshot shares it.
                Err(ReceiveError::ExceedsMaxBorrows) if newest.is_some() => break,
                Err(ReceiveError::ExceedsMaxBorrows) if self.holds_newest_alone() => {
                    self.current = None;
                }
                Err(e) => return Err(ClientError::Receive(e)),
            }
        }
        let Some(s) = newest else {
            return Ok(false);
        };
        let s = std::rc::Rc::new(s);
        let held = HeldSnapshot::new(s.clone());
        self.current = Some((s, held));
        Ok(true)
    }

    /// Whether the newest sample is referenced only by `current` (its `Rc` and the
    /// validated `HeldSnapshot` beside it), not by a snapshot handed out.
    fn holds_newest_alone(&self) -> bool {
        self.current
            .as_ref()
            .is_some_and(|(s, _)| std::rc::Rc::strong_count(s) <= 2)
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
        match &self.current {
            None => Ok(None),
            Some((_, Ok(held))) => Ok(Some(held.view())),
            Some((_, Err(e))) => Err(ClientError::Snapshot(*e)),
        }
    }

    /// [`Self::latest`] as a handle that stays valid after later receives.
    pub fn latest_held(&mut self) -> Result<Option<HeldSnapshot>, ClientError> {
        self.poll()?;
        match &self.current {
            None => Ok(None),
            Some((_, Ok(held))) => Ok(Some(held.clone())),
            Some((_, Err(e))) => Err(ClientError::Snapshot(*e)),
        }
    }

    /// The wire header of the held sample (sequence, length, when it was published).
    pub fn wire_header(&self) -> Option<SnapshotHeader> {
        self.current.as_ref().map(|(s, _)| *s.user_header())
    }

    /// The whole shared-memory payload of the held sample (to check it is not a copy).
    pub fn sample_bytes(&self) -> Option<&[u8]> {
        self.current.as_ref().map(|(s, _)| s.payload())
    }
}

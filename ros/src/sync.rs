//! Clouds matched to their poses, as tf2's message filter does: each cloud waits until the
//! TF buffer can give the transform from the map frame to the cloud's frame at its stamp,
//! or until the recording has moved on by the wait time, then comes out posed or dropped
//! with the reason. Clouds come out in the order they went in.

use crate::cloud::{self, CloudError, CloudPoints};
use crate::msg::{self, DecodeError, Odometry, PointCloud2, PoseStamped, TfMessage, Time};
use crate::tf::{InsertError, LookupError, TfBuffer};
use nalgebra::Isometry3;
use std::collections::VecDeque;

/// Where poses come from.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum PoseSource {
    /// `/tf` and `/tf_static`.
    Tf,
    /// A pose topic (`nav_msgs/msg/Odometry` or `geometry_msgs/msg/PoseStamped`) gives the
    /// dynamic link from its `header.frame_id` to its child frame (the odometry's
    /// `child_frame_id`; for a `PoseStamped`, `pose_frame`). `/tf_static` still gives the
    /// rest; `/tf` samples for that same child are ignored.
    Topic {
        topic: String,
        pose_frame: Option<String>,
    },
}

/// How clouds are matched to poses.
#[derive(Debug, Clone)]
pub struct SyncConfig {
    /// The frame the map is built in (tf2's target frame).
    pub map_frame: String,
    /// How long (recording time) a cloud waits for its transform.
    pub wait_ns: i64,
    pub poses: PoseSource,
}

impl Default for SyncConfig {
    fn default() -> Self {
        Self {
            map_frame: "map".into(),
            wait_ns: 1_000_000_000,
            poses: PoseSource::Tf,
        }
    }
}

/// A cloud with its pose in the map frame.
#[derive(Debug, Clone)]
pub struct PosedCloud {
    pub topic: String,
    /// Index of the cloud among its topic's messages (from 0).
    pub index: u64,
    pub stamp: Time,
    pub frame_id: String,
    pub pose: Isometry3<f64>,
    pub points: CloudPoints,
}

/// Why a cloud was dropped.
#[derive(Debug, Clone, PartialEq)]
pub enum DropReason {
    Decode(DecodeError),
    Cloud(CloudError),
    Transform(LookupError),
}

impl DropReason {
    /// A short name of the reason, for counting.
    pub fn kind(&self) -> String {
        match self {
            Self::Decode(_) => "not a PointCloud2".into(),
            Self::Cloud(e) => e.kind().into(),
            Self::Transform(e) => format!("no transform ({})", e.kind()),
        }
    }
}

impl std::fmt::Display for DropReason {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Decode(e) => write!(f, "cannot decode: {e}"),
            Self::Cloud(e) => e.fmt(f),
            Self::Transform(e) => write!(f, "no transform: {e}"),
        }
    }
}

/// A dropped cloud: which, and why.
#[derive(Debug, Clone, PartialEq)]
pub struct Dropped {
    pub topic: String,
    pub index: u64,
    pub reason: DropReason,
}

impl std::fmt::Display for Dropped {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{} cloud {}: {}", self.topic, self.index, self.reason)
    }
}

impl std::error::Error for Dropped {}

/// A TF or pose message that could not go into the buffer.
#[derive(Debug, Clone, PartialEq)]
pub enum TfRejected {
    Decode(DecodeError),
    Insert(InsertError),
    /// A `PoseStamped` pose topic without a pose frame.
    NoPoseFrame,
}

impl std::fmt::Display for TfRejected {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Decode(e) => write!(f, "cannot decode: {e}"),
            Self::Insert(e) => e.fmt(f),
            Self::NoPoseFrame => f.write_str(
                "a PoseStamped has no child frame: say which frame it gives the pose of",
            ),
        }
    }
}

struct Pending {
    topic: String,
    index: u64,
    log_time_ns: u64,
    cloud: PointCloud2<Vec<u8>>,
}

/// Most clouds waiting at once; beyond, the oldest is resolved with what the buffer has.
const MAX_PENDING: usize = 256;

/// The message filter. Feed it every TF, pose and cloud message in recording order, then
/// take what is [`ready`](Self::ready); at the end, [`finish`](Self::finish).
pub struct CloudSync {
    config: SyncConfig,
    tf: TfBuffer,
    pending: VecDeque<Pending>,
    /// Resolved, not yet taken by `ready`; all older than anything pending.
    done: Vec<Result<PosedCloud, Dropped>>,
    now_ns: u64,
    pose_child: Option<String>,
}

impl CloudSync {
    pub fn new(config: SyncConfig) -> Self {
        Self {
            config,
            tf: TfBuffer::default(),
            pending: VecDeque::new(),
            done: Vec::new(),
            now_ns: 0,
            pose_child: None,
        }
    }

    /// The TF buffer (for `inspect`'s tree).
    pub fn tf(&self) -> &TfBuffer {
        &self.tf
    }

    /// Move the clock on to `now_ns` (it never goes back): live input calls this before
    /// [`ready`](Self::ready), so that clouds time out while no message arrives.
    pub fn advance(&mut self, now_ns: u64) {
        self.now_ns = self.now_ns.max(now_ns);
    }

    /// A serialized `tf2_msgs/msg/TFMessage` from `/tf` (`is_static` false) or
    /// `/tf_static`. Returns the transforms it could not take (the others went in).
    pub fn tf_message(
        &mut self,
        log_time_ns: u64,
        data: &[u8],
        is_static: bool,
    ) -> Vec<TfRejected> {
        match msg::decode(data) {
            Ok(m) => self.tf_transforms(log_time_ns, &m, is_static),
            Err(e) => {
                self.advance(log_time_ns);
                vec![TfRejected::Decode(e)]
            }
        }
    }

    /// A decoded `TFMessage`, as [`tf_message`](Self::tf_message).
    pub fn tf_transforms(
        &mut self,
        log_time_ns: u64,
        m: &TfMessage,
        is_static: bool,
    ) -> Vec<TfRejected> {
        self.advance(log_time_ns);
        let mut bad = Vec::new();
        for t in &m.transforms {
            if !is_static && self.pose_child.as_deref() == Some(t.child_frame_id.as_str()) {
                continue;
            }
            if let Err(e) = self.tf.insert(
                &t.header.frame_id,
                &t.child_frame_id,
                t.header.stamp,
                &t.transform,
                is_static,
            ) {
                bad.push(TfRejected::Insert(e));
            }
        }
        bad
    }

    /// A message of the pose topic, of type `type_name` (Odometry or PoseStamped).
    pub fn pose_message(
        &mut self,
        log_time_ns: u64,
        type_name: &str,
        data: &[u8],
    ) -> Result<(), TfRejected> {
        self.advance(log_time_ns);
        let (parent, child, stamp, pose) = if type_name == msg::types::ODOMETRY {
            let o: Odometry = msg::decode(data).map_err(TfRejected::Decode)?;
            (
                o.header.frame_id.to_owned(),
                o.child_frame_id.to_owned(),
                o.header.stamp,
                o.pose.pose,
            )
        } else {
            let p: PoseStamped = msg::decode(data).map_err(TfRejected::Decode)?;
            let child = match &self.config.poses {
                PoseSource::Topic {
                    pose_frame: Some(f),
                    ..
                } => f.clone(),
                _ => return Err(TfRejected::NoPoseFrame),
            };
            (p.header.frame_id, child, p.header.stamp, p.pose)
        };
        self.pose_child.get_or_insert_with(|| child.clone());
        self.tf
            .insert(&parent, &child, stamp, &pose, false)
            .map_err(TfRejected::Insert)
    }

    /// A serialized cloud message: posed at once if its transform is there and no older
    /// cloud waits, else queued (a copy) until it is. A message that is not a PointCloud2
    /// is dropped at once.
    pub fn cloud(
        &mut self,
        topic: &str,
        index: u64,
        log_time_ns: u64,
        data: &[u8],
    ) -> Result<(), Dropped> {
        match msg::decode::<PointCloud2<&[u8]>>(data) {
            Ok(c) => {
                self.decoded_cloud(topic, index, log_time_ns, c);
                Ok(())
            }
            Err(e) => {
                self.advance(log_time_ns);
                Err(Dropped {
                    topic: topic.into(),
                    index,
                    reason: DropReason::Decode(e),
                })
            }
        }
    }

    /// A decoded cloud, as [`cloud`](Self::cloud); its data is kept (`Vec<u8>` without a
    /// copy, `&[u8]` copied) only if it has to wait.
    pub fn decoded_cloud<D: AsRef<[u8]> + Into<Vec<u8>>>(
        &mut self,
        topic: &str,
        index: u64,
        log_time_ns: u64,
        c: PointCloud2<D>,
    ) {
        self.advance(log_time_ns);
        if self.pending.is_empty() {
            let map = &self.config.map_frame;
            if let Ok(pose) = self.tf.lookup(map, &c.header.frame_id, c.header.stamp) {
                self.done.push(posed(topic.into(), index, c, pose));
                return;
            }
        }
        self.pending.push_back(Pending {
            topic: topic.into(),
            index,
            log_time_ns,
            cloud: c.map_data(Into::into),
        });
    }

    /// Clouds whose wait is over, in order: each posed, or dropped with the reason.
    pub fn ready(&mut self) -> Vec<Result<PosedCloud, Dropped>> {
        let mut out = std::mem::take(&mut self.done);
        while let Some(p) = self.pending.front() {
            let lookup = self.tf.lookup(
                &self.config.map_frame,
                &p.cloud.header.frame_id,
                p.cloud.header.stamp,
            );
            let waited = self.now_ns.saturating_sub(p.log_time_ns) as i64 > self.config.wait_ns;
            if lookup.is_err() && !waited && self.pending.len() <= MAX_PENDING {
                break;
            }
            if let Some(p) = self.pending.pop_front() {
                out.push(resolve(p, lookup));
            }
        }
        out
    }

    /// Every cloud still waiting, resolved with what the buffer has: the end of the input.
    pub fn finish(&mut self) -> Vec<Result<PosedCloud, Dropped>> {
        let mut out = std::mem::take(&mut self.done);
        while let Some(p) = self.pending.pop_front() {
            let lookup = self.tf.lookup(
                &self.config.map_frame,
                &p.cloud.header.frame_id,
                p.cloud.header.stamp,
            );
            out.push(resolve(p, lookup));
        }
        out
    }
}

fn resolve(p: Pending, lookup: Result<Isometry3<f64>, LookupError>) -> Result<PosedCloud, Dropped> {
    let drop = |reason| Dropped {
        topic: p.topic.clone(),
        index: p.index,
        reason,
    };
    let pose = lookup.map_err(|e| drop(DropReason::Transform(e)))?;
    posed(p.topic, p.index, p.cloud, pose)
}

/// Cloud `index` of `topic`, decoded as `c`, read into points at `pose`.
fn posed(
    topic: String,
    index: u64,
    c: PointCloud2<impl AsRef<[u8]>>,
    pose: Isometry3<f64>,
) -> Result<PosedCloud, Dropped> {
    match cloud::points(&c) {
        Ok(points) => Ok(PosedCloud {
            topic,
            index,
            stamp: c.header.stamp,
            frame_id: c.header.frame_id,
            pose,
            points,
        }),
        Err(e) => Err(Dropped {
            topic,
            index,
            reason: DropReason::Cloud(e),
        }),
    }
}

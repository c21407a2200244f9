//! A TF buffer as tf2 keeps one: each frame's link to its parent, static (valid at any
//! time) or dynamic (stamped samples, interpolated between the two around a lookup's time:
//! linear in translation, slerp in rotation, never extrapolated), and lookups that walk the
//! tree from both frames to their common ancestor.

use crate::msg::{Time, Transform};
use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion, Vector3};
use std::collections::{HashMap, VecDeque};

/// How long a dynamic link keeps its samples, as tf2's default cache time: 10 s behind
/// its newest.
pub const DEFAULT_CACHE_NS: i64 = 10_000_000_000;

/// The most links a lookup walks from one frame before it calls the tree a loop (tf2's
/// limit too).
const MAX_DEPTH: usize = 1000;

type FrameId = u32;

#[derive(Clone, Copy, Debug)]
struct Sample {
    stamp: i64,
    parent: FrameId,
    pose: Isometry3<f64>,
}

#[derive(Default, Debug)]
struct Link {
    fixed: Option<(FrameId, Isometry3<f64>)>,
    samples: VecDeque<Sample>,
}

/// A transform that cannot go into the buffer.
#[derive(Debug, Clone, PartialEq)]
pub enum InsertError {
    EmptyFrameId,
    /// A frame's parent is itself.
    SelfParent(String),
    /// A NaN or infinite translation or rotation component.
    NonFinite {
        child: String,
    },
    /// A rotation whose squared length is not within 0.01 of 1 (tf2's tolerance).
    NotUnit {
        child: String,
        norm: f64,
    },
}

impl std::fmt::Display for InsertError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::EmptyFrameId => f.write_str("a transform with an empty frame id"),
            Self::SelfParent(c) => write!(f, "frame '{c}' is given itself as parent"),
            Self::NonFinite { child } => write!(f, "the transform to '{child}' is not finite"),
            Self::NotUnit { child, norm } => write!(
                f,
                "the transform to '{child}' has a rotation of length {norm} (not a unit quaternion)"
            ),
        }
    }
}

impl std::error::Error for InsertError {}

/// Why a lookup found no transform.
#[derive(Debug, Clone, PartialEq)]
pub enum LookupError {
    /// No transform has named the frame, as parent or child.
    UnknownFrame(String),
    /// Both frames exist but their trees have different roots.
    NotConnected { target: String, source: String },
    /// The lookup time is outside a dynamic link's samples.
    Extrapolation {
        parent: String,
        child: String,
        stamp_ns: i64,
        earliest_ns: i64,
        latest_ns: i64,
    },
    /// A chain of more than 1000 links: the parents form a loop.
    Loop(String),
}

impl LookupError {
    /// A short name of the kind of failure, for counting by reason.
    pub fn kind(&self) -> &'static str {
        match self {
            Self::UnknownFrame(_) => "unknown frame",
            Self::NotConnected { .. } => "frames not connected",
            Self::Extrapolation {
                stamp_ns,
                earliest_ns,
                ..
            } if stamp_ns < earliest_ns => "extrapolation into the past",
            Self::Extrapolation { .. } => "extrapolation into the future",
            Self::Loop(_) => "loop in the TF tree",
        }
    }
}

fn secs(ns: i64) -> f64 {
    ns as f64 * 1e-9
}

impl std::fmt::Display for LookupError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::UnknownFrame(n) => write!(f, "frame '{n}' does not exist in the TF tree"),
            Self::NotConnected { target, source } => write!(
                f,
                "frames '{target}' and '{source}' are not part of the same tree"
            ),
            Self::Extrapolation {
                parent,
                child,
                stamp_ns,
                earliest_ns,
                latest_ns,
            } => write!(
                f,
                "{}: the link {parent} -> {child} has samples from {:.9} to {:.9} s only, \
                 lookup at {:.9} s",
                self.kind(),
                secs(*earliest_ns),
                secs(*latest_ns),
                secs(*stamp_ns)
            ),
            Self::Loop(n) => write!(f, "the parents of frame '{n}' form a loop"),
        }
    }
}

impl std::error::Error for LookupError {}

/// One link of the tree, for `voxmap inspect`.
#[derive(Debug, Clone, PartialEq)]
pub struct LinkInfo {
    pub parent: String,
    pub child: String,
    pub is_static: bool,
    /// Dynamic links: samples held, and the first and last stamp.
    pub samples: usize,
    pub stamps_ns: Option<(i64, i64)>,
}

/// A TF tree over time. See the module doc.
#[derive(Debug)]
pub struct TfBuffer {
    ids: HashMap<String, FrameId>,
    names: Vec<String>,
    links: Vec<Link>,
    cache_ns: i64,
}

impl Default for TfBuffer {
    fn default() -> Self {
        Self::new(DEFAULT_CACHE_NS)
    }
}

/// The isometry of a ROS transform (or pose), after tf2's checks; rotations within
/// tolerance are normalised.
pub fn isometry(t: &Transform) -> Result<Isometry3<f64>, (bool, f64)> {
    let (v, q) = (t.translation, t.rotation);
    let all = [v.x, v.y, v.z, q.x, q.y, q.z, q.w];
    if all.iter().any(|c| !c.is_finite()) {
        return Err((false, f64::NAN));
    }
    let q = Quaternion::new(q.w, q.x, q.y, q.z);
    let n2 = q.norm_squared();
    if (n2 - 1.0).abs() > 0.01 {
        return Err((true, n2.sqrt()));
    }
    Ok(Isometry3::from_parts(
        Translation3::new(v.x, v.y, v.z),
        UnitQuaternion::from_quaternion(q),
    ))
}

impl TfBuffer {
    /// An empty buffer whose dynamic links keep `cache_ns` of samples.
    pub fn new(cache_ns: i64) -> Self {
        Self {
            ids: HashMap::new(),
            names: Vec::new(),
            links: Vec::new(),
            cache_ns: cache_ns.max(0),
        }
    }

    fn id(&mut self, name: &str) -> FrameId {
        if let Some(&i) = self.ids.get(name) {
            return i;
        }
        let i = self.names.len() as FrameId;
        self.ids.insert(name.to_owned(), i);
        self.names.push(name.to_owned());
        self.links.push(Link::default());
        i
    }

    /// Add the pose `transform` of `child` in `parent` at `stamp` (any time if static).
    /// A leading `/` on a frame id is dropped, as tf2 does.
    pub fn insert(
        &mut self,
        parent: &str,
        child: &str,
        stamp: Time,
        transform: &Transform,
        is_static: bool,
    ) -> Result<(), InsertError> {
        let (parent, child) = (strip(parent), strip(child));
        if parent.is_empty() || child.is_empty() {
            return Err(InsertError::EmptyFrameId);
        }
        if parent == child {
            return Err(InsertError::SelfParent(child.into()));
        }
        let pose = isometry(transform).map_err(|(unit, norm)| {
            if unit {
                InsertError::NotUnit {
                    child: child.into(),
                    norm,
                }
            } else {
                InsertError::NonFinite {
                    child: child.into(),
                }
            }
        })?;
        let (p, c) = (self.id(parent), self.id(child));
        let link = &mut self.links[c as usize];
        if is_static {
            link.fixed = Some((p, pose));
            return Ok(());
        }
        let s = Sample {
            stamp: stamp.ns(),
            parent: p,
            pose,
        };
        let q = &mut link.samples;
        let i = q.partition_point(|x| x.stamp <= s.stamp);
        if i > 0 && q[i - 1].stamp == s.stamp {
            q[i - 1] = s;
        } else {
            q.insert(i, s);
        }
        let newest = q.back().map_or(s.stamp, |x| x.stamp);
        while q.len() > 1
            && q.front()
                .is_some_and(|x| x.stamp < newest.saturating_sub(self.cache_ns))
        {
            q.pop_front();
        }
        Ok(())
    }

    /// The frame's link at `t`: its parent and its pose in the parent, or `None` for a root.
    fn link_at(
        &self,
        frame: FrameId,
        t: i64,
    ) -> Result<Option<(FrameId, Isometry3<f64>)>, LookupError> {
        let link = &self.links[frame as usize];
        let q = &link.samples;
        let (Some(first), Some(last)) = (q.front(), q.back()) else {
            return Ok(link.fixed);
        };
        let err = || LookupError::Extrapolation {
            parent: self.names[first.parent as usize].clone(),
            child: self.names[frame as usize].clone(),
            stamp_ns: t,
            earliest_ns: first.stamp,
            latest_ns: last.stamp,
        };
        if t < first.stamp || t > last.stamp {
            return Err(err());
        }
        let i = q.partition_point(|x| x.stamp <= t);
        let a = q[i - 1];
        if a.stamp == t {
            return Ok(Some((a.parent, a.pose)));
        }
        let b = q[i];
        if a.parent != b.parent {
            // A reparented frame: tf2 does not interpolate across the change either.
            return Ok(Some((a.parent, a.pose)));
        }
        let s = (t - a.stamp) as f64 / (b.stamp - a.stamp) as f64;
        Ok(Some((a.parent, interpolate(&a.pose, &b.pose, s))))
    }

    /// The latest time at which every dynamic link between the frames has a sample (tf2's
    /// meaning of a lookup at time 0), or `None` if the links are all static.
    fn latest_common(&self, frames: [FrameId; 2]) -> Option<i64> {
        let mut t: Option<i64> = None;
        for mut f in frames {
            for _ in 0..MAX_DEPTH {
                let link = &self.links[f as usize];
                let parent = match link.samples.back() {
                    Some(s) => {
                        t = Some(t.map_or(s.stamp, |t| t.min(s.stamp)));
                        s.parent
                    }
                    None => match link.fixed {
                        Some((p, _)) => p,
                        None => break,
                    },
                };
                f = parent;
            }
        }
        t
    }

    /// The pose of `source` in `target` at `stamp`: what maps points in `source` to
    /// `target` (tf2's `lookupTransform(target, source, stamp)`). Time 0 means the latest
    /// time all links have, as in tf2.
    pub fn lookup(
        &self,
        target: &str,
        source: &str,
        stamp: Time,
    ) -> Result<Isometry3<f64>, LookupError> {
        let (target, source) = (strip(target), strip(source));
        if target == source {
            return Ok(Isometry3::identity());
        }
        let find = |n: &str| {
            self.ids
                .get(n)
                .copied()
                .ok_or_else(|| LookupError::UnknownFrame(n.to_owned()))
        };
        let (tg, sr) = (find(target)?, find(source)?);
        let t = match stamp.ns() {
            0 => self.latest_common([tg, sr]).unwrap_or(0),
            t => t,
        };
        // The chain from the source up to its root: each ancestor with the source's pose in it.
        let mut up: Vec<(FrameId, Isometry3<f64>)> = vec![(sr, Isometry3::identity())];
        let mut f = sr;
        let mut acc = Isometry3::identity();
        while let Some((p, pose)) = self.link_at(f, t)? {
            acc = pose * acc;
            up.push((p, acc));
            f = p;
            if up.len() > MAX_DEPTH {
                return Err(LookupError::Loop(source.into()));
            }
        }
        // Up from the target until the first frame on the source's chain.
        let (mut f, mut acc, mut depth) = (tg, Isometry3::identity(), 0);
        loop {
            if let Some((_, src_in_f)) = up.iter().find(|(a, _)| *a == f) {
                return Ok(acc.inverse() * src_in_f);
            }
            match self.link_at(f, t)? {
                Some((p, pose)) => {
                    acc = pose * acc;
                    f = p;
                }
                None => {
                    return Err(LookupError::NotConnected {
                        target: target.into(),
                        source: source.into(),
                    })
                }
            }
            depth += 1;
            if depth > MAX_DEPTH {
                return Err(LookupError::Loop(target.into()));
            }
        }
    }

    /// Every link, in the order their child frames first appeared.
    pub fn links(&self) -> Vec<LinkInfo> {
        let mut out = Vec::new();
        for (c, link) in self.links.iter().enumerate() {
            let child = self.names[c].clone();
            if let Some((p, _)) = link.fixed {
                out.push(LinkInfo {
                    parent: self.names[p as usize].clone(),
                    child: child.clone(),
                    is_static: true,
                    samples: 0,
                    stamps_ns: None,
                });
            }
            if let (Some(a), Some(b)) = (link.samples.front(), link.samples.back()) {
                out.push(LinkInfo {
                    parent: self.names[b.parent as usize].clone(),
                    child,
                    is_static: false,
                    samples: link.samples.len(),
                    stamps_ns: Some((a.stamp, b.stamp)),
                });
            }
        }
        out
    }
}

fn strip(frame: &str) -> &str {
    frame.strip_prefix('/').unwrap_or(frame)
}

/// Between `a` (s = 0) and `b` (s = 1): translation linear, rotation along the shorter arc.
pub fn interpolate(a: &Isometry3<f64>, b: &Isometry3<f64>, s: f64) -> Isometry3<f64> {
    let ta: Vector3<f64> = a.translation.vector;
    let t = ta + (b.translation.vector - ta) * s;
    let (qa, mut qb) = (a.rotation, b.rotation);
    if qa.coords.dot(&qb.coords) < 0.0 {
        qb = UnitQuaternion::new_unchecked(-qb.into_inner());
    }
    // After the flip the two are at most 90 degrees apart on the sphere, so slerp is defined.
    let r = qa.try_slerp(&qb, s, 1e-12).unwrap_or(qa);
    Isometry3::from_parts(Translation3::from(t), r)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::msg::{Quaternion as Q, Vector3 as V};

    fn tf(x: f64, y: f64, z: f64, yaw: f64) -> Transform {
        let (s, c) = (yaw / 2.0).sin_cos();
        Transform {
            translation: V { x, y, z },
            rotation: Q {
                x: 0.0,
                y: 0.0,
                z: s,
                w: c,
            },
        }
    }

    fn at(sec: i32, nanosec: u32) -> Time {
        Time { sec, nanosec }
    }

    fn close(a: &Isometry3<f64>, b: &Isometry3<f64>) -> bool {
        (a.translation.vector - b.translation.vector).norm() < 1e-12
            && a.rotation.angle_to(&b.rotation) < 1e-12
    }

    /// map -(static)-> odom -(dynamic)-> base -(static)-> cam, and a second branch
    /// base -> wheel. Lookups through the chain, between branches, and interpolated.
    #[test]
    fn chains_are_composed_and_dynamic_links_interpolated() {
        let mut b = TfBuffer::default();
        b.insert("map", "odom", at(0, 0), &tf(10.0, 0.0, 0.0, 0.0), true)
            .unwrap();
        b.insert("odom", "base", at(1, 0), &tf(0.0, 0.0, 0.0, 0.0), false)
            .unwrap();
        b.insert(
            "odom",
            "base",
            at(2, 0),
            &tf(2.0, 0.0, 0.0, std::f64::consts::FRAC_PI_2),
            false,
        )
        .unwrap();
        b.insert("/base", "cam", at(0, 0), &tf(0.0, 1.0, 0.5, 0.0), true)
            .unwrap();
        b.insert("base", "wheel", at(0, 0), &tf(0.0, -1.0, 0.0, 0.0), true)
            .unwrap();
        // Halfway: base at x = 1, yaw 45 degrees; cam 1 m to its left and 0.5 up.
        let p = b.lookup("map", "cam", at(1, 500_000_000)).unwrap();
        let yaw = std::f64::consts::FRAC_PI_4;
        let want = Isometry3::from_parts(
            Translation3::new(11.0 - yaw.sin(), yaw.cos(), 0.5),
            UnitQuaternion::from_euler_angles(0.0, 0.0, yaw),
        );
        assert!(close(&p, &want), "{p} vs {want}");
        // Between two branches: the camera in the wheel's frame does not move.
        let w = b.lookup("wheel", "cam", at(1, 700_000_000)).unwrap();
        assert!(close(&w, &Isometry3::translation(0.0, 2.0, 0.5)));
        // The inverse lookup is the inverse.
        let inv = b.lookup("cam", "map", at(1, 500_000_000)).unwrap();
        assert!(close(&inv, &want.inverse()));
        // Exactly at a sample, and time 0 = the latest sample.
        let end = b.lookup("odom", "base", at(2, 0)).unwrap();
        assert!(close(&end, &b.lookup("odom", "base", at(0, 0)).unwrap()));
    }

    #[test]
    fn lookups_that_tf2_refuses_are_refused_with_the_reason() {
        let mut b = TfBuffer::default();
        b.insert("odom", "base", at(1, 0), &tf(0.0, 0.0, 0.0, 0.0), false)
            .unwrap();
        b.insert("odom", "base", at(2, 0), &tf(1.0, 0.0, 0.0, 0.0), false)
            .unwrap();
        b.insert("other", "x", at(0, 0), &tf(0.0, 0.0, 0.0, 0.0), true)
            .unwrap();
        let e = b.lookup("odom", "base", at(2, 1)).unwrap_err();
        assert_eq!(e.kind(), "extrapolation into the future");
        assert!(e.to_string().contains("odom -> base"), "{e}");
        assert_eq!(
            b.lookup("odom", "base", at(0, 999_999_999))
                .unwrap_err()
                .kind(),
            "extrapolation into the past"
        );
        assert_eq!(
            b.lookup("map", "base", at(1, 0)).unwrap_err(),
            LookupError::UnknownFrame("map".into())
        );
        assert_eq!(
            b.lookup("odom", "x", at(1, 0)).unwrap_err().kind(),
            "frames not connected"
        );
        // Bad transforms do not go in.
        let mut nan = tf(0.0, 0.0, 0.0, 0.0);
        nan.translation.x = f64::NAN;
        assert!(matches!(
            b.insert("a", "b", at(1, 0), &nan, false),
            Err(InsertError::NonFinite { .. })
        ));
        let mut zero = tf(0.0, 0.0, 0.0, 0.0);
        zero.rotation.w = 0.0;
        assert!(matches!(
            b.insert("a", "b", at(1, 0), &zero, false),
            Err(InsertError::NotUnit { .. })
        ));
        assert!(matches!(
            b.insert("a", "a", at(1, 0), &tf(0.0, 0.0, 0.0, 0.0), true),
            Err(InsertError::SelfParent(_))
        ));
        assert!(b.lookup("a", "b", at(1, 0)).is_err());
    }

    #[test]
    fn the_cache_keeps_ten_seconds_behind_the_newest_sample() {
        let mut b = TfBuffer::default();
        for s in 0..30 {
            b.insert(
                "odom",
                "base",
                at(s, 0),
                &tf(f64::from(s), 0.0, 0.0, 0.0),
                false,
            )
            .unwrap();
        }
        let l = &b.links()[0];
        assert_eq!(l.stamps_ns, Some((19_000_000_000, 29_000_000_000)));
        assert_eq!(
            b.lookup("odom", "base", at(18, 0)).unwrap_err().kind(),
            "extrapolation into the past"
        );
        // A sample arriving out of order goes in its place.
        b.insert(
            "odom",
            "base",
            at(25, 500_000_000),
            &tf(100.0, 0.0, 0.0, 0.0),
            false,
        )
        .unwrap();
        let p = b.lookup("odom", "base", at(25, 500_000_000)).unwrap();
        assert_eq!(p.translation.x, 100.0);
    }

    #[test]
    fn slerp_takes_the_short_way_round() {
        let a = Isometry3::from_parts(
            Translation3::identity(),
            UnitQuaternion::from_euler_angles(0.0, 0.0, 3.0),
        );
        // The same rotation as yaw -3.0 + 2 pi, written with the opposite quaternion sign.
        let qb = UnitQuaternion::from_euler_angles(0.0, 0.0, -3.0);
        let b = Isometry3::from_parts(
            Translation3::identity(),
            UnitQuaternion::new_unchecked(-qb.into_inner()),
        );
        let m = interpolate(&a, &b, 0.5);
        // Halfway the short way between yaw 3.0 and yaw 2pi - 3.0 is yaw pi.
        assert!(
            (m.rotation.angle() - std::f64::consts::PI).abs() < 1e-9,
            "{}",
            m.rotation.angle()
        );
    }
}

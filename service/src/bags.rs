//! ROS 2 bags for `voxmap replay` and `voxmap inspect`: which topics to read, the clouds
//! posed from TF (or a pose topic) by `voxmap_ros::sync`, and a bag's description.

use crate::replay::{Read, Scan};
use anyhow::{anyhow, bail, Result};
use clap::Args;
use std::collections::HashMap;
use std::ops::ControlFlow;
use std::path::Path;
use voxmap_ros::bag::{Bag, TopicInfo};
use voxmap_ros::msg::types;
use voxmap_ros::sync::{CloudSync, PoseSource, SyncConfig};
use voxmap_ros::tf::TfBuffer;

const TF: &str = "/tf";
const TF_STATIC: &str = "/tf_static";

/// How `voxmap replay` reads a ROS 2 bag.
#[derive(Args, Debug, Clone)]
pub struct BagArgs {
    /// Bag: the sensor_msgs/msg/PointCloud2 topic(s) to map (default: the bag's only one).
    #[arg(long = "topic")]
    pub topics: Vec<String>,
    /// Bag: the frame the map is built in; each cloud's pose is the transform from it to
    /// the cloud's frame at the cloud's stamp.
    #[arg(long, default_value = "map")]
    pub map_frame: String,
    /// Bag: take the moving link from this nav_msgs/msg/Odometry or
    /// geometry_msgs/msg/PoseStamped topic instead of /tf (/tf_static still gives the rest).
    #[arg(long)]
    pub pose_topic: Option<String>,
    /// Bag: the frame a PoseStamped --pose-topic gives the pose of (an Odometry names its
    /// own child frame).
    #[arg(long)]
    pub pose_frame: Option<String>,
    /// Bag: how long (seconds of recording) a cloud waits for its transform before it is
    /// dropped, as tf2's message filter.
    #[arg(long, default_value_t = 1.0)]
    pub tf_wait: f64,
}

/// A bag and what to read from it.
pub struct BagPlan {
    pub bag: Bag,
    pub clouds: Vec<String>,
    /// Cloud messages the bag says it holds on those topics.
    pub cloud_count: Option<u64>,
    config: SyncConfig,
}

fn list(topics: &[&TopicInfo]) -> String {
    if topics.is_empty() {
        return "none".into();
    }
    topics
        .iter()
        .map(|t| t.name.as_str())
        .collect::<Vec<_>>()
        .join(", ")
}

impl BagPlan {
    pub fn new(path: &Path, a: &BagArgs) -> Result<Self> {
        let bag = Bag::open(path)?;
        let clouds_in_bag: Vec<&TopicInfo> = bag.topics_of_type(types::POINT_CLOUD2).collect();
        let clouds: Vec<String> = if a.topics.is_empty() {
            match clouds_in_bag.as_slice() {
                [one] => vec![one.name.clone()],
                [] => bail!(
                    "{}: no {} topic in the bag (topics: {})",
                    path.display(),
                    types::POINT_CLOUD2,
                    list(&bag.topics.iter().collect::<Vec<_>>())
                ),
                many => bail!(
                    "{}: {} PointCloud2 topics; choose with --topic: {}",
                    path.display(),
                    many.len(),
                    list(many)
                ),
            }
        } else {
            for t in &a.topics {
                if !clouds_in_bag.iter().any(|c| &c.name == t) {
                    bail!(
                        "{}: no PointCloud2 topic '{t}' (PointCloud2 topics: {})",
                        path.display(),
                        list(&clouds_in_bag)
                    );
                }
            }
            a.topics.clone()
        };
        let poses = match &a.pose_topic {
            None => PoseSource::Tf,
            Some(p) => {
                let t = bag.topics.iter().find(|t| &t.name == p).ok_or_else(|| {
                    anyhow!("{}: no topic '{p}' for --pose-topic", path.display())
                })?;
                if t.type_name == types::POSE_STAMPED && a.pose_frame.is_none() {
                    bail!(
                        "{p} is a PoseStamped, which does not name the frame it is the pose of: \
                         give it with --pose-frame"
                    );
                }
                if t.type_name != types::ODOMETRY && t.type_name != types::POSE_STAMPED {
                    bail!(
                        "--pose-topic {p} is a {}; expected {} or {}",
                        t.type_name,
                        types::ODOMETRY,
                        types::POSE_STAMPED
                    );
                }
                PoseSource::Topic {
                    topic: p.clone(),
                    pose_frame: a.pose_frame.clone(),
                }
            }
        };
        if !(a.tf_wait.is_finite() && (0.0..=3600.0).contains(&a.tf_wait)) {
            bail!("--tf-wait must be 0..3600 seconds, not {}", a.tf_wait);
        }
        let cloud_count = clouds
            .iter()
            .map(|c| {
                bag.topics
                    .iter()
                    .find(|t| &t.name == c)
                    .and_then(|t| t.count)
            })
            .sum();
        Ok(Self {
            config: SyncConfig {
                map_frame: a.map_frame.clone(),
                wait_ns: (a.tf_wait * 1e9) as i64,
                poses,
            },
            bag,
            clouds,
            cloud_count,
        })
    }

    /// Read the bag through, sending each posed cloud, dropped cloud, ignored transform and
    /// damaged file to `send` in order; stop when `send` returns false.
    pub fn read(&self, send: &mut dyn FnMut(Read) -> bool) {
        let pose_topic = match &self.config.poses {
            PoseSource::Topic { topic, .. } => Some(topic.clone()),
            PoseSource::Tf => None,
        };
        let wanted = |t: &str| {
            t == TF
                || t == TF_STATIC
                || self.clouds.iter().any(|c| c == t)
                || pose_topic.as_deref() == Some(t)
        };
        let mut sync = CloudSync::new(self.config.clone());
        let mut index: HashMap<String, u64> = HashMap::new();
        let mut open = true;
        for i in 0..self.bag.files.len() {
            let r = self.bag.read_file(i, &wanted, &mut |m| {
                if m.topic == TF || m.topic == TF_STATIC {
                    for bad in sync.tf_message(m.log_time_ns, m.data, m.topic == TF_STATIC) {
                        open &= send(Read::TfRejected(format!("{}: {bad}", m.topic)));
                    }
                } else if pose_topic.as_deref() == Some(m.topic) {
                    if let Err(bad) = sync.pose_message(m.log_time_ns, m.type_name, m.data) {
                        open &= send(Read::TfRejected(format!("{}: {bad}", m.topic)));
                    }
                } else {
                    let k = index.entry(m.topic.to_owned()).or_default();
                    let n = *k;
                    *k += 1;
                    if let Err(d) = sync.cloud(m.topic, n, m.log_time_ns, m.data) {
                        open &= send(skip(d));
                    }
                }
                for r in sync.ready() {
                    open &= send(posed(r));
                }
                if open {
                    ControlFlow::Continue(())
                } else {
                    ControlFlow::Break(())
                }
            });
            if !open {
                return;
            }
            if let Err(e) = r {
                if !send(Read::Damaged(e.into())) {
                    return;
                }
            }
        }
        for r in sync.finish() {
            if !send(posed(r)) {
                return;
            }
        }
    }
}

fn skip(d: voxmap_ros::sync::Dropped) -> Read {
    Read::Skip {
        kind: d.reason.kind(),
        error: d.into(),
    }
}

fn posed(r: Result<voxmap_ros::sync::PosedCloud, voxmap_ros::sync::Dropped>) -> Read {
    match r {
        Ok(c) => Read::Scan(Scan {
            name: format!("{} cloud {}", c.topic, c.index),
            non_finite: c.points.non_finite,
            points: c.points.points,
            pose: c.pose,
            stamp: Some(c.stamp.ns() as f64 * 1e-9),
        }),
        Err(d) => skip(d),
    }
}

fn time(ns: u64) -> String {
    format!("{:.3} s", ns as f64 * 1e-9)
}

/// `voxmap inspect BAG`: files, topics with types and counts, time span, and the TF tree.
pub fn inspect(path: &Path) -> Result<()> {
    let bag = Bag::open(path)?;
    println!("{}", path.display());
    println!("  {:<20} ROS 2 bag, {} file(s)", "format", bag.files.len());
    for f in &bag.files {
        let size = std::fs::metadata(&f.path).map(|m| m.len()).unwrap_or(0);
        println!(
            "  {:<20} {} ({}, {size} bytes)",
            "file",
            f.path.display(),
            f.storage
        );
    }
    if let Some((a, b)) = bag.span_ns {
        println!(
            "  {:<20} {} .. {} ({:.3} s)",
            "time span",
            time(a),
            time(b),
            b.saturating_sub(a) as f64 * 1e-9
        );
    }
    println!("  topics:");
    for t in &bag.topics {
        let n = t.count.map_or("?".into(), |n| n.to_string());
        println!("    {:<32} {:<36} {n:>8} messages", t.name, t.type_name);
    }
    // The TF tree, from every /tf and /tf_static message, with nothing dropped from the cache.
    let mut tf = TfBuffer::new(i64::MAX);
    let mut rejected = 0u64;
    let mut damage = Vec::new();
    for i in 0..bag.files.len() {
        let r = bag.read_file(i, &|t| t == TF || t == TF_STATIC, &mut |m| {
            let Ok(msg) = voxmap_ros::msg::decode::<voxmap_ros::msg::TfMessage>(m.data) else {
                rejected += 1;
                return ControlFlow::Continue(());
            };
            for t in &msg.transforms {
                let s = m.topic == TF_STATIC;
                if tf
                    .insert(
                        &t.header.frame_id,
                        &t.child_frame_id,
                        t.header.stamp,
                        &t.transform,
                        s,
                    )
                    .is_err()
                {
                    rejected += 1;
                }
            }
            ControlFlow::Continue(())
        });
        if let Err(e) = r {
            damage.push(format!("{:#}", anyhow::Error::from(e)));
        }
    }
    let links = tf.links();
    println!("  TF tree ({} links):", links.len());
    for l in &links {
        match (l.is_static, l.stamps_ns) {
            (true, _) => println!("    {} -> {}  static", l.parent, l.child),
            (false, Some((a, b))) => println!(
                "    {} -> {}  dynamic, {} samples, {} .. {}",
                l.parent,
                l.child,
                l.samples,
                time(a.max(0) as u64),
                time(b.max(0) as u64)
            ),
            (false, None) => {}
        }
    }
    if rejected > 0 {
        println!("  {rejected} transforms could not be read");
    }
    for d in damage {
        println!("  damaged: {d}");
    }
    Ok(())
}

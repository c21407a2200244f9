//! The `[ros2]` settings of `voxmap serve --ros2`, as the TOML file spells them.

use serde::{Deserialize, Serialize};

/// One cloud topic to map.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CloudTopic {
    pub topic: String,
    /// Points farther than this (metres) from this sensor are left out of its frames; the
    /// service's own `max_range` still cuts the rest. None: only the service's applies.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub max_range: Option<f64>,
}

impl std::str::FromStr for CloudTopic {
    type Err = String;

    /// `TOPIC` or `TOPIC@RANGE` (metres), as `--ros2-cloud-topic` takes it.
    fn from_str(s: &str) -> Result<Self, String> {
        let (topic, max_range) = match s.rsplit_once('@') {
            None => (s, None),
            Some((t, r)) => {
                let r: f64 = r
                    .parse()
                    .map_err(|_| format!("'{s}': the max range after '@' is not a number"))?;
                (t, Some(r))
            }
        };
        let c = CloudTopic {
            topic: topic.to_string(),
            max_range,
        };
        c.check()?;
        Ok(c)
    }
}

impl CloudTopic {
    fn check(&self) -> Result<(), String> {
        if !self.topic.starts_with('/') || self.topic.len() < 2 || self.topic.ends_with('/') {
            return Err(format!(
                "cloud topic '{}': give an absolute ROS 2 name such as /camera/depth/points",
                self.topic
            ));
        }
        if let Some(r) = self.max_range {
            if !(r.is_finite() && r > 0.0) {
                return Err(format!(
                    "cloud topic '{}': max_range must be > 0",
                    self.topic
                ));
            }
        }
        Ok(())
    }
}

/// How services map onto DDS topics: as `rmw_fastrtps_cpp` (Fast DDS, the default of
/// Jazzy and Kilted) and `rmw_connextdds` do, or as `rmw_cyclonedds_cpp` does.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ServiceMappingName {
    Enhanced,
    Cyclone,
}

/// Every `[ros2]` setting.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Ros2Config {
    /// PointCloud2 topics to map.
    pub cloud_topics: Vec<CloudTopic>,
    /// The frame the map is built in (tf2's target frame) and the outputs' frame.
    pub map_frame: String,
    /// How long a cloud waits for its transform before it is dropped and counted.
    pub tf_timeout_ms: f64,
    /// The outputs are published at most this often, from the newest snapshot.
    pub publish_period_ms: f64,
    /// `/voxmap/grid` projects the voxels whose centres lie in this z range (metres).
    pub grid_z_min: f64,
    pub grid_z_max: f64,
    /// The ROS 2 node's name (its namespace is `/`).
    pub node_name: String,
    pub service_mapping: ServiceMappingName,
}

impl Default for Ros2Config {
    fn default() -> Self {
        Self {
            cloud_topics: Vec::new(),
            map_frame: "map".into(),
            tf_timeout_ms: 500.0,
            publish_period_ms: 500.0,
            grid_z_min: 0.05,
            grid_z_max: 2.0,
            node_name: "voxmap".into(),
            service_mapping: ServiceMappingName::Enhanced,
        }
    }
}

impl Ros2Config {
    /// Settings that cannot work, with what is wrong.
    pub fn check(&self) -> Result<(), String> {
        for t in &self.cloud_topics {
            t.check()?;
        }
        if self.map_frame.is_empty() {
            return Err("ros2.map_frame is empty".into());
        }
        if !(0.0..=60_000.0).contains(&self.tf_timeout_ms) {
            return Err("ros2.tf_timeout_ms must be in [0, 60000]".into());
        }
        if !(1.0..=3.6e6).contains(&self.publish_period_ms) {
            return Err("ros2.publish_period_ms must be in [1, 3.6e6]".into());
        }
        if !(self.grid_z_min.is_finite() && self.grid_z_max.is_finite())
            || self.grid_z_min > self.grid_z_max
        {
            return Err("ros2.grid_z_min must be <= ros2.grid_z_max, both finite".into());
        }
        if ros2_client::NodeName::new("/", &self.node_name).is_err() {
            return Err(format!(
                "ros2.node_name '{}' is not a ROS 2 node name",
                self.node_name
            ));
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cloud_topics_parse_with_and_without_a_range() {
        let t: CloudTopic = "/lidar/points".parse().unwrap();
        assert_eq!((t.topic.as_str(), t.max_range), ("/lidar/points", None));
        let t: CloudTopic = "/camera/depth/points@4.5".parse().unwrap();
        assert_eq!(
            (t.topic.as_str(), t.max_range),
            ("/camera/depth/points", Some(4.5))
        );
        for bad in ["points", "/a@x", "/a@-1", "/", "/a/"] {
            assert!(bad.parse::<CloudTopic>().is_err(), "{bad}");
        }
    }

    #[test]
    fn defaults_pass_and_bad_settings_say_which() {
        Ros2Config::default().check().unwrap();
        let c = Ros2Config {
            grid_z_min: 3.0,
            ..Default::default()
        };
        assert!(c.check().unwrap_err().contains("grid_z_min"));
        let c = Ros2Config {
            node_name: "no spaces".into(),
            ..Default::default()
        };
        assert!(c.check().unwrap_err().contains("node_name"));
    }
}

//! Live ROS 2 for voxmap, over DDS in pure Rust (`ros2-client` on `rustdds`; no ROS
//! installation): `sensor_msgs/msg/PointCloud2` and TF in, the map out as
//! `/voxmap/occupied` (PointCloud2), `/voxmap/octomap_binary` (`octomap_msgs/msg/Octomap`)
//! and `/voxmap/grid` (`nav_msgs/msg/OccupancyGrid`), with map services under `/voxmap/`.
//!
//! The bridge is a client of the voxmap service like any other: posed clouds go in as
//! shared-memory frames (the service's own validation, counters and intake policy), and
//! the outputs are encoded from the snapshots it publishes. Modules: [`config`] (the
//! `[ros2]` settings), [`discovery`] (`ROS_DOMAIN_ID`, `ROS_AUTOMATIC_DISCOVERY_RANGE`,
//! `ROS_STATIC_PEERS`), [`interfaces`] (the services' types), [`outputs`] (snapshot to
//! messages) and [`bridge`] (the loop that ties them together).

pub mod bridge;
pub mod config;
pub mod discovery;
pub mod interfaces;
pub mod outputs;

pub use bridge::{Bridge, BridgeCounters, MapTopicsReader};
pub use config::{CloudTopic, Ros2Config, ServiceMappingName};

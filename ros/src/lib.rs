//! ROS 2 data for voxmap without a ROS installation: rosbag2 bags in both storages
//! ([`bag`]), the messages voxmap reads and their CDR decoding ([`msg`]),
//! `sensor_msgs/msg/PointCloud2` to points ([`cloud`]), a tf2-style TF buffer ([`tf`]) and
//! the message filter that poses each cloud from it ([`sync`]).
//!
//! Shared by `voxmap replay` (bags) and the live ROS 2 bridge.

pub mod bag;
pub mod cloud;
pub mod msg;
pub mod sync;
pub mod tf;

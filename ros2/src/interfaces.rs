//! The services the bridge offers under `/voxmap/`, and their request and response types
//! in CDR field order. `reset_map` is `std_srvs/srv/Trigger`; the others are
//! `voxmap_msgs/srv/*`, whose `.srv` files (an ament package) are in
//! `ros2/voxmap_msgs/` for a ROS workspace to build, so that `ros2 service call` knows them.

use ros2_client::Message;
use serde::{Deserialize, Serialize};
use voxmap_ros::msg::Vector3;

/// The namespace of every output topic and service.
pub const NAMESPACE: &str = "/voxmap";

/// `std_srvs/srv/Trigger` request (an empty message: ROS 2 gives it one placeholder byte).
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct TriggerRequest {
    pub structure_needs_at_least_one_member: u8,
}

/// `std_srvs/srv/Trigger` response; also the response of `SaveMap` and `LoadMap`.
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct Outcome {
    pub success: bool,
    pub message: String,
}

/// `voxmap_msgs/srv/SaveMap` and `LoadMap` request: the map file.
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct PathRequest {
    pub path: String,
}

/// `voxmap_msgs/srv/Raytrace` request: a ray through the newest snapshot.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct RaytraceRequest {
    /// `geometry_msgs/Point`, map frame.
    pub origin: Vector3,
    /// `geometry_msgs/Vector3`, any non-zero length.
    pub direction: Vector3,
    /// Metres along `direction`.
    pub max_length: f64,
}

/// `voxmap_msgs/srv/Raytrace` response.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct RaytraceResponse {
    /// False when the ray could not be cast (see `message`); `hit` and `end_point` then
    /// mean nothing.
    pub success: bool,
    /// The ray met an occupied voxel within `max_length`.
    pub hit: bool,
    /// The centre of the first occupied voxel, or the ray's end when there is none.
    pub end_point: Vector3,
    pub message: String,
}

impl Message for TriggerRequest {}
impl Message for Outcome {}
impl Message for PathRequest {}
impl Message for RaytraceRequest {}
impl Message for RaytraceResponse {}

//! File formats: PCD point clouds.
pub mod pcd;

//! File formats: PCD point clouds, map files and snapshot files.
pub mod mapfile;
pub mod pcd;

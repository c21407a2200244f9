//! File formats: PCD, PLY and KITTI point clouds with pose files, map files, snapshot
//! files and OctoMap `.bt`.
mod error;
pub mod mapfile;
pub mod octomap;
pub mod pcd;
pub mod ply;
pub mod scans;

pub use error::{Format, ParseError, ReadError, ReadErrorKind};

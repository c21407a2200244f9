//! Arbitrary bytes as each recorded-scan format voxmap reads: PCD, PLY, KITTI `.bin` and a
//! pose file (TUM or KITTI lines). Parsing must never panic; what parses is points or poses.
#![no_main]

use libfuzzer_sys::fuzz_target;
use voxmap_map::io::{pcd, ply, scans};

fuzz_target!(|data: &[u8]| {
    if let Ok(c) = pcd::parse(data) {
        let _ = pcd::parse(&pcd::encode(&c));
    }
    let _ = ply::parse(data);
    if let Ok(p) = scans::parse_kitti_bin(data) {
        assert_eq!(p.len(), data.len() / 16);
    }
    if let Ok(text) = std::str::from_utf8(data) {
        let _ = scans::parse_poses(text);
    }
});

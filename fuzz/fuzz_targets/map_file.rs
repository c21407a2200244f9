//! Arbitrary bytes as a map file: decoding must never panic, and a map it accepts must
//! encode and decode again to the same voxels.
#![no_main]

use libfuzzer_sys::fuzz_target;
use voxmap_core::io::mapfile::{decode_map, encode_map};

fuzz_target!(|data: &[u8]| {
    if let Ok(map) = decode_map(data) {
        let again = decode_map(&encode_map(&map)).expect("a re-encoded map decodes");
        let voxels = |m: &voxmap_core::OccupancyMap| {
            let mut v: Vec<_> = m
                .grid()
                .active_voxels()
                .map(|(c, x)| (c.to_array(), x))
                .collect();
            v.sort();
            v
        };
        assert_eq!(voxels(&map), voxels(&again));
    }
});

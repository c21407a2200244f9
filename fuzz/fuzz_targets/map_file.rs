//! Arbitrary bytes as a map file: decoding must never panic, and a map (and distance
//! field) it accepts must encode and decode again to the same voxels (and field).
#![no_main]

use libfuzzer_sys::fuzz_target;
use voxmap_map::io::mapfile::{decode_map_with_field, encode_map_parts_with};

fuzz_target!(|data: &[u8]| {
    if let Ok((map, field)) = decode_map_with_field(data) {
        let bytes = encode_map_parts_with(&map, field.as_ref()).into_bytes();
        let (again, field_again) = decode_map_with_field(&bytes).expect("a re-encoded map decodes");
        assert_eq!(field.map(|f| f.band_voxels()), field_again.map(|f| f.band_voxels()));
        let voxels = |m: &voxmap_map::OccupancyMap| {
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

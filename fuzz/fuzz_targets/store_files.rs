//! Arbitrary bytes as a tile store's files: a tile record (`record::decode`, then its
//! leaves), raw leaf records past the checksums (`record::leaves_of`), and a manifest
//! (`store::decode_manifest`): each must give a clear error or a checked value, never
//! panic.
#![no_main]

use libfuzzer_sys::fuzz_target;
use voxmap_map::store::{decode_manifest, record};
use voxmap_map::{SensorModel, VoxelCoord};

fuzz_target!(|data: &[u8]| {
    let q = SensorModel::default().quantize().expect("the default model quantizes");
    if let Ok((head, raw)) = record::decode(data) {
        assert_eq!(raw.len(), head.raw_len as usize);
        if let Ok(leaves) = record::leaves_of(&raw, head.tile, &q) {
            assert_eq!(leaves.len(), head.leaves as usize);
        }
    }
    if let Ok(leaves) = record::leaves_of(data, VoxelCoord::new(0, 0, 0), &q) {
        assert!(leaves.len() <= 4096);
        assert!(leaves.windows(2).all(|w| w[0].0 != w[1].0));
    }
    if let Ok(m) = decode_manifest(data) {
        assert!(m.params.resolution > 0.0);
    }
});

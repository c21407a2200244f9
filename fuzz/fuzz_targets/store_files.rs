//! Arbitrary bytes as a tile store's files: a tile record (`record::decode`, then its
//! leaves and bands, then the bands restored into a distance field), raw leaf records past
//! the checksums (`record::leaves_of`), band records past them (`record::bands_of`), and a
//! manifest (`store::decode_manifest`): each must give a clear error or a checked value,
//! never panic.
#![no_main]

use libfuzzer_sys::fuzz_target;
use voxmap_map::field::{DistanceField, FieldConfig};
use voxmap_map::store::{decode_manifest, record};
use voxmap_map::{SensorModel, VoxelCoord};

fuzz_target!(|data: &[u8]| {
    let q = SensorModel::default().quantize().expect("the default model quantizes");
    let restore = |rec: record::TileRecord| {
        let mut field = DistanceField::new(FieldConfig::default(), 0.1).expect("a field");
        let n = rec.bands.len();
        if field.restore_tile(&rec.leaves, rec.bands).is_ok() {
            assert!(field.leaves().count() <= n);
        }
    };
    if let Ok((head, raw)) = record::decode(data) {
        assert_eq!(raw.bytes.len(), head.raw_len as usize);
        if let Ok(rec) = raw.decode(head.tile, &q) {
            assert_eq!(rec.leaves.len(), head.leaves as usize);
            restore(rec);
        }
    }
    if let Ok(leaves) = record::leaves_of(data, VoxelCoord::new(0, 0, 0), &q) {
        assert!(leaves.len() <= 4096);
        assert!(leaves.windows(2).all(|w| w[0].0 != w[1].0));
    }
    // Band records after the leaf records of the first bytes.
    let cut = data.len().min(usize::from(data.first().copied().unwrap_or(0)) * 8);
    let (leaf_part, band_part) = data.split_at(cut - cut % voxmap_map::io::mapfile::RECORD);
    if let Ok(leaves) = record::leaves_of(leaf_part, VoxelCoord::new(0, 0, 0), &q) {
        if let Ok(bands) = record::bands_of(band_part, &leaves) {
            assert!(bands.len() <= leaves.len());
            restore(record::TileRecord { leaves, bands });
        }
    }
    if let Ok(m) = decode_manifest(data) {
        assert!(m.params.resolution > 0.0);
    }
});

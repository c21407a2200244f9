//! Arbitrary bytes into `SnapshotView::open` and then every query, the distance field's
//! too: must never panic.
#![no_main]

use libfuzzer_sys::fuzz_target;
use voxmap_map::snapshot::SnapshotView;
use voxmap_map::{VoxelCoord, WorldPoint};

fuzz_target!(|data: &[u8]| {
    let _ = SnapshotView::open_checked(data);
    if let Ok(v) = SnapshotView::open(data) {
        let voxels: Vec<_> = (-16..16).map(|i| VoxelCoord::new(i * 5, -i * 3, i)).collect();
        let mut batched = Vec::new();
        v.states(&voxels, &mut batched);
        for (p, s) in voxels.iter().zip(batched) {
            assert_eq!(v.state(*p), s, "batched and single lookups disagree");
            let _ = v.probability(*p);
        }
        let _ = v.first_hit(&WorldPoint::new(-2.0, -1.0, 0.5), &WorldPoint::new(3.0, 2.0, -1.0), true);
        // Unknown not blocking: leaves with nothing occupied are jumped.
        let _ = v.first_hit(&WorldPoint::new(-6.0, 0.3, 0.2), &WorldPoint::new(6.0, -0.4, 0.1), false);
        let _ = v.is_box_free(&WorldPoint::new(-1.0, -1.0, -1.0), &WorldPoint::new(1.0, 1.0, 1.0), false);
        let _ = v.is_box_free(&WorldPoint::new(-1e5, -1e5, -1e5), &WorldPoint::new(1e5, 1e5, 1e5), true);
        let _ = v.occupied_voxels().take(10_000).count();
        let _ = (v.bounds(), v.counts());
        // The distance field section, when the bytes claim one.
        if let Some(f) = v.distance_field() {
            let points: Vec<_> = (-16..16)
                .map(|i| WorldPoint::new(0.13 * f64::from(i), -0.07 * f64::from(i), 0.05 * f64::from(i)))
                .collect();
            let (mut d, mut g, mut n) = (Vec::new(), Vec::new(), Vec::new());
            f.distances_at(&points, &mut d);
            f.distances_and_gradients_at(&points, &mut g);
            f.nearest_obstacles(&points, &mut n);
            for p in &voxels {
                let _ = f.distance(*p);
            }
        }
    }
});

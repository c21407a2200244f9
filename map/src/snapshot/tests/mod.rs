//! The snapshot writer and view together: maps written and read back, and bytes that lie.

use super::*;
use crate::coord::{VoxelCoord, WorldPoint};
use crate::model::VoxelState;
use crate::raycast::find_voxel;
use crate::test_rng::Rng;
use crate::{Frame, Integrator, IntegratorConfig, OccupancyMap, RayMode, SensorModel};
use nalgebra::{Isometry3, Translation3, UnitQuaternion};
use proptest::prelude::*;

mod bytes;
mod field;
mod queries;

/// A map from a few random posed frames around the origin (negative coordinates too).
fn random_map(seed: u64, frames: usize) -> OccupancyMap {
    let mut rng = Rng(seed);
    let mut map = OccupancyMap::new(0.1, SensorModel::default()).unwrap();
    let mut integ = Integrator::new(IntegratorConfig {
        threads: 2,
        max_range: 4.0,
        mode: RayMode::Exact,
        ..Default::default()
    })
    .unwrap();
    for _ in 0..frames {
        let pose = Isometry3::from_parts(
            Translation3::new(rng.f() * 2.0 - 1.0, rng.f() * 2.0 - 1.0, rng.f() - 0.5),
            UnitQuaternion::from_euler_angles(rng.f(), rng.f(), rng.f() * 6.0),
        );
        let pts: Vec<[f32; 3]> = (0..3000)
            .map(|_| [0, 1, 2].map(|_| (rng.f() * 9.0 - 4.5) as f32))
            .collect();
        integ
            .integrate(&mut map, &Frame { pose, points: &pts })
            .unwrap();
    }
    // Some known voxels at the occupancy threshold and either side of it: at it is occupied.
    let t = map.quantized().threshold;
    let some: Vec<VoxelCoord> = map
        .grid()
        .active_voxels()
        .map(|(v, _)| v)
        .take(600)
        .collect();
    for (i, v) in some.into_iter().enumerate() {
        map.set_value(v, t - 1 + (i % 3) as i8);
    }
    map.assert_marks_in_step();
    map
}

fn encode(map: &OccupancyMap, scope: Scope, with_values: bool) -> Vec<u8> {
    Plan::new(
        map,
        scope,
        Meta {
            sequence: 42,
            timestamp_ns: 7,
            with_values,
        },
    )
    .to_vec()
}

fn with_field(map: &OccupancyMap, scope: Scope, unknown: crate::field::UnknownPolicy) -> Vec<u8> {
    let cfg = crate::field::FieldConfig {
        max_distance: 0.5,
        unknown,
        window: None,
    };
    let mut field = crate::field::DistanceField::new(cfg, map.resolution()).unwrap();
    field.rebuild(map, None);
    Plan::new(map, scope, Meta::default())
        .with_field(&field)
        .to_vec()
}

/// Bytes of the field section, which runs from the first 8-byte boundary after the last
/// other section to the end of a snapshot.
fn field_section_len(bytes: &[u8]) -> usize {
    let v = SnapshotView::open(bytes).unwrap();
    assert!(v.distance_field().is_some());
    let h = v.header();
    let values_end = match h.flags & layout::FLAG_VALUES {
        0 => 0,
        _ => h.values_offset + 512 * h.leaf_count,
    };
    let end = (h.masks_offset + layout::align8(h.masks_len)).max(values_end);
    bytes.len() - layout::align8(end) as usize
}

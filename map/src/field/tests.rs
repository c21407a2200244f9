//! The distance field against a brute-force nearest-obstacle search, and its incremental
//! updates against a build from scratch.

use super::*;
use crate::coord::{VoxelCoord, WorldPoint};
use crate::model::{SensorModel, VoxelState};
use crate::test_rng::Rng;
use crate::{Frame, Integrator, IntegratorConfig, OccupancyMap};
use hashbrown::HashMap;
use nalgebra::{Isometry3, Translation3, UnitQuaternion};

/// The nearest obstacle of `v` by scanning every voxel within `r`, with the field's
/// tie-break: smallest (d², dx, dy), then the lower z. Unknown voxels are obstacles under
/// `Occupied`, wherever they are.
fn brute(map: &OccupancyMap, v: VoxelCoord, r: i32, policy: UnknownPolicy) -> Option<[i8; 3]> {
    let mut best: Option<(i32, i32, i32, bool, [i8; 3])> = None;
    for dz in -r..=r {
        for dy in -r..=r {
            for dx in -r..=r {
                let d2 = dx * dx + dy * dy + dz * dz;
                if d2 >= r * r {
                    continue;
                }
                let obstacle = match map.state(v + VoxelCoord::new(dx, dy, dz)) {
                    VoxelState::Occupied => true,
                    VoxelState::Unknown => policy == UnknownPolicy::Occupied,
                    VoxelState::Free => false,
                };
                let key = (d2, dx, dy, dz > 0, [dx as i8, dy as i8, dz as i8]);
                if obstacle
                    && best.is_none_or(|b| (key.0, key.1, key.2, key.3) < (b.0, b.1, b.2, b.3))
                {
                    best = Some(key);
                }
            }
        }
    }
    best.map(|b| b.4)
}

/// A map of random free and occupied voxels in a box, with whole leaves left unknown and
/// partly known leaves.
fn random_map(seed: u64, lo: i32, hi: i32, occupied: f64) -> OccupancyMap {
    let mut map = OccupancyMap::new(0.1, SensorModel::default()).unwrap();
    let mut rng = Rng(seed);
    for z in lo..=hi {
        for y in lo..=hi {
            for x in lo..=hi {
                // Leaves at (8, *, *) stay unknown; elsewhere a tenth of voxels.
                if (x >> 3) == 1 || rng.f() < 0.1 {
                    continue;
                }
                let value = if rng.f() < occupied { 100 } else { -100 };
                map.set_value(VoxelCoord::new(x, y, z), value);
            }
        }
    }
    map
}

/// Every voxel of the map's leaves: the field equals the brute force, and is `None` where
/// the brute force finds nothing.
fn assert_matches_brute(map: &OccupancyMap, field: &DistanceField) {
    let r = field.radius() as i32;
    let policy = field.config().unknown;
    let mut checked = 0;
    for (origin, _) in map.grid().leaves() {
        for i in 0..512 {
            let v = crate::tree::voxel_at(origin, i);
            assert_eq!(
                field.nearest(v),
                brute(map, v, r, policy),
                "voxel {v:?}, {policy:?}"
            );
            checked += 1;
        }
    }
    assert!(checked > 1000, "only {checked} voxels checked");
}

#[test]
fn equals_brute_force_on_random_maps() {
    for (seed, occ, r, policy) in [
        (1, 0.02, 5, UnknownPolicy::Free),
        (2, 0.002, 7, UnknownPolicy::Free),
        (3, 0.3, 3, UnknownPolicy::Free),
        (4, 0.01, 4, UnknownPolicy::Occupied),
    ] {
        let map = random_map(seed, -20, 20, occ);
        let cfg = FieldConfig {
            max_distance: f64::from(r) * 0.1,
            unknown: policy,
            window: None,
        };
        let mut field = DistanceField::new(cfg, 0.1).unwrap();
        field.rebuild(&map, None);
        assert!(field.band_voxels() > 0);
        assert_matches_brute(&map, &field);
    }
}

#[test]
fn ties_and_axis_extremes_are_exact() {
    // Two obstacles equally far from the voxel between them, one above and one below;
    // and an obstacle exactly at the radius (outside the band), one just inside.
    let mut map = OccupancyMap::new(0.1, SensorModel::default()).unwrap();
    for z in -8..8 {
        for x in -8..8 {
            map.set_value(VoxelCoord::new(x, 0, z), -100);
        }
    }
    map.set_value(VoxelCoord::new(0, 0, 3), 100);
    map.set_value(VoxelCoord::new(0, 0, -3), 100);
    let cfg = FieldConfig {
        max_distance: 0.5,
        ..Default::default()
    };
    let mut field = DistanceField::new(cfg, 0.1).unwrap();
    field.rebuild(&map, None);
    assert_eq!(field.nearest(VoxelCoord::new(0, 0, 0)), Some([0, 0, -3]));
    assert_eq!(field.nearest(VoxelCoord::new(4, 0, 3)), Some([-4, 0, 0]));
    assert_eq!(
        field.nearest(VoxelCoord::new(5, 0, 3)),
        None,
        "5 voxels is the radius"
    );
    assert_eq!(field.nearest(VoxelCoord::new(0, 0, 3)), Some([0, 0, 0]));
    assert_eq!(
        field.distance(VoxelCoord::new(3, 0, 3)),
        Some(0.30000000000000004)
    );
    assert_eq!(
        field.nearest(VoxelCoord::new(3, 0, 7)),
        None,
        "(-3, 0, -4) is 5 voxels away"
    );
    assert_matches_brute(&map, &field);
}

fn scan(rng: &mut Rng, n: usize) -> Vec<[f32; 3]> {
    (0..n)
        .map(|_| {
            // Walls of a box room with some clutter.
            let p = rng.ball(1.0);
            let s = 2.5 / p.iter().map(|c| c.abs()).fold(0.0, f32::max).max(1e-3);
            let k = if rng.f() < 0.2 {
                0.4 + rng.f() as f32 * 0.5
            } else {
                1.0
            };
            p.map(|c| c * s * k)
        })
        .collect()
}

fn pose(rng: &mut Rng) -> Isometry3<f64> {
    Isometry3::from_parts(
        Translation3::new(rng.f() - 0.5, rng.f() - 0.5, rng.f() * 0.3),
        UnitQuaternion::from_euler_angles(0.1 * rng.f(), 0.1 * rng.f(), 6.0 * rng.f()),
    )
}

/// The band as a map from voxel to offset.
fn band(field: &DistanceField) -> HashMap<VoxelCoord, [i8; 3]> {
    let mut out = HashMap::new();
    for (o, band) in field.leaves() {
        for (i, offset) in band.iter() {
            let v = crate::tree::voxel_at(o, i);
            if field.covers(v) {
                out.insert(v, offset);
            }
        }
    }
    out
}

#[test]
fn incremental_updates_equal_a_rebuild_for_any_thread_count() {
    for policy in [UnknownPolicy::Free, UnknownPolicy::Occupied] {
        let cfg = FieldConfig {
            max_distance: 0.6,
            unknown: policy,
            window: None,
        };
        let mut results = Vec::new();
        for threads in [1, 3] {
            let mut map = OccupancyMap::new(0.1, SensorModel::default()).unwrap();
            let mut integ = Integrator::new(IntegratorConfig {
                threads,
                max_range: 4.0,
                ..Default::default()
            })
            .unwrap();
            let mut field = DistanceField::new(cfg, 0.1).unwrap();
            let mut rng = Rng(7);
            for k in 0..6 {
                let points = scan(&mut rng, 4000);
                let frame = Frame {
                    pose: pose(&mut rng),
                    points: &points,
                };
                let report = integ.integrate(&mut map, &frame).unwrap();
                let fr = integ.install(|| field.update(&map, report.bounds, None));
                if k > 0 {
                    assert!(fr.patches > 0 && fr.changed_leaves > 0, "{fr:?}");
                }
            }
            let mut fresh = DistanceField::new(cfg, 0.1).unwrap();
            fresh.rebuild(&map, None);
            let got = band(&field);
            assert_eq!(got, band(&fresh), "{policy:?}, {threads} threads");
            // Spot-check against the brute force.
            let mut rng = Rng(11);
            let leaves: Vec<VoxelCoord> = map.grid().leaves().map(|(o, _)| o).collect();
            for _ in 0..3000 {
                let o = leaves[rng.i(0, leaves.len() as i32 - 1) as usize];
                let v = crate::tree::voxel_at(o, rng.i(0, 511) as usize);
                assert_eq!(field.nearest(v), brute(&map, v, 6, policy), "{v:?}");
            }
            results.push(got);
        }
        assert_eq!(results[0], results[1]);
    }
}

#[test]
fn a_window_moves_with_the_sensor_and_holds_the_rebuilt_field_inside() {
    let cfg = FieldConfig {
        max_distance: 0.5,
        unknown: UnknownPolicy::Free,
        window: Some([1.5, 1.5, 1.0]),
    };
    let mut map = OccupancyMap::new(0.1, SensorModel::default()).unwrap();
    let mut integ = Integrator::new(IntegratorConfig {
        threads: 2,
        max_range: 4.0,
        ..Default::default()
    })
    .unwrap();
    let mut field = DistanceField::new(cfg, 0.1).unwrap();
    let mut rng = Rng(3);
    let mut frame_at = |x: f64, map: &mut OccupancyMap, field: &mut DistanceField| {
        let points = scan(&mut rng, 3000);
        let p = Isometry3::translation(x, 0.0, 0.0);
        let report = integ
            .integrate(
                map,
                &Frame {
                    pose: p,
                    points: &points,
                },
            )
            .unwrap();
        let sensor = WorldPoint::from(p.translation.vector);
        integ.install(|| field.update(map, report.bounds, Some(sensor)));
    };
    for k in 0..5 {
        frame_at(0.7 * k as f64, &mut map, &mut field);
    }
    let (lo, hi) = field.window().expect("placed");
    assert_eq!(lo, VoxelCoord::new(13, -15, -10));
    assert_eq!(hi, VoxelCoord::new(43, 15, 10));
    assert_holds_the_rebuilt_field(&map, &field);
    assert_eq!(
        field.nearest(VoxelCoord::new(0, 0, 0)),
        None,
        "outside the window"
    );
    // Back over ground whose obstacles the frames changed while the window was away: the
    // obstacles kept for leaves outside it tell which.
    for x in [2.1, 1.0, 0.0] {
        frame_at(x, &mut map, &mut field);
    }
    assert_holds_the_rebuilt_field(&map, &field);
    assert!(field.covers(VoxelCoord::new(0, 0, 0)));
}

/// A windowed field holds, inside its window, exactly the field rebuilt over the whole map,
/// and counts the band voxels it stores.
fn assert_holds_the_rebuilt_field(map: &OccupancyMap, field: &DistanceField) {
    let cfg = FieldConfig {
        window: None,
        ..*field.config()
    };
    let mut whole = DistanceField::new(cfg, map.resolution()).unwrap();
    whole.rebuild(map, None);
    let inside: HashMap<_, _> = band(&whole)
        .into_iter()
        .filter(|(v, _)| field.covers(*v))
        .collect();
    assert!(!inside.is_empty());
    assert_eq!(band(field), inside);
    let stored: u64 = field.leaves().map(|(_, b)| b.offsets().len() as u64).sum();
    assert_eq!(field.band_voxels(), stored);
}

#[test]
fn a_leaf_answers_each_voxel_from_its_packed_offsets() {
    let map = random_map(5, -12, 12, 0.02);
    let mut field = DistanceField::new(
        FieldConfig {
            max_distance: 0.4,
            ..FieldConfig::default()
        },
        0.1,
    )
    .unwrap();
    field.rebuild(&map, None);
    let mut partial = 0;
    for (_, band) in field.leaves() {
        let by_voxel: HashMap<usize, [i8; 3]> = band.iter().collect();
        partial += usize::from(by_voxel.len() < 512);
        for i in 0..512 {
            assert_eq!(band.get(i), by_voxel.get(&i).copied(), "voxel {i}");
        }
    }
    assert!(partial > 0, "no leaf only partly in the band");
}

#[test]
fn bad_configurations_are_refused() {
    for (d, w) in [
        (0.04, None),
        (6.4, None),
        (f64::NAN, None),
        (1.0, Some([1.0, 0.0, 1.0])),
        (1.0, Some([1.0, f64::INFINITY, 1.0])),
    ] {
        let cfg = FieldConfig {
            max_distance: d,
            window: w,
            ..Default::default()
        };
        assert!(DistanceField::new(cfg, 0.1).is_err(), "{d} {w:?}");
    }
    assert_eq!(
        DistanceField::new(FieldConfig::default(), 0.1)
            .unwrap()
            .radius(),
        20
    );
}

#[test]
fn obstacles_that_change_outside_the_window_reach_into_it() {
    let cfg = FieldConfig {
        max_distance: 0.8,
        unknown: UnknownPolicy::Free,
        window: Some([1.0, 1.0, 1.0]),
    };
    let mut map = OccupancyMap::new(0.1, SensorModel::default()).unwrap();
    for x in -24..32 {
        for y in -4..4 {
            map.set_value(VoxelCoord::new(x, y, 0), -10);
        }
    }
    let edge = VoxelCoord::new(10, 0, 0);
    let (a, b) = (VoxelCoord::new(16, 0, 0), VoxelCoord::new(17, 1, 0));
    map.set_value(a, 100);
    let mut field = DistanceField::new(cfg, 0.1).unwrap();
    let at = |x: f64| Some(WorldPoint::new(x, 0.0, 0.0));
    field.update(&map, None, at(0.0));
    assert_eq!(
        field.window(),
        Some((VoxelCoord::new(-10, -10, -10), VoxelCoord::new(10, 10, 10)))
    );
    assert!(!field.covers(a), "the obstacle lies outside the window");
    assert_eq!(field.nearest(edge), Some([6, 0, 0]));
    let only = |v: VoxelCoord| Some((v, v));
    // The obstacle goes, another comes, both outside the window; then the window takes
    // them in and leaves them again.
    map.set_value(a, -10);
    field.update(&map, only(a), at(0.0));
    assert_eq!(field.nearest(edge), None);
    map.set_value(b, 100);
    field.update(&map, only(b), at(0.0));
    assert_eq!(field.nearest(edge), Some([7, 1, 0]));
    field.update(&map, None, at(1.5));
    assert_eq!(field.nearest(b), Some([0, 0, 0]));
    map.set_value(b, -10);
    field.update(&map, only(b), at(0.0));
    assert_eq!(field.nearest(edge), None);
    map.set_value(a, 100);
    field.update(&map, only(a), at(0.0));
    assert_eq!(field.nearest(edge), Some([6, 0, 0]));
    assert_holds_the_rebuilt_field(&map, &field);
}

#[test]
fn a_leaf_the_window_leaves_keeps_its_obstacles_for_the_next_update() {
    let cfg = FieldConfig {
        max_distance: 0.8,
        unknown: UnknownPolicy::Free,
        window: Some([4.0, 4.0, 4.0]),
    };
    let mut map = OccupancyMap::new(0.1, SensorModel::default()).unwrap();
    for x in -56..64 {
        map.set_value(VoxelCoord::new(x, 0, 0), -10);
    }
    let (edge, b) = (VoxelCoord::new(-32, 0, 0), VoxelCoord::new(-36, 0, 0));
    map.set_value(b, 100);
    let mut field = DistanceField::new(cfg, 0.1).unwrap();
    field.update(&map, None, Some(WorldPoint::new(0.0, 0.0, 0.0)));
    assert_eq!(field.nearest(edge), Some([-4, 0, 0]));
    // The window moves so that `b`'s leaf falls out of it while the patch of `edge` stays
    // covered (no transform for the move alone), and `b` goes in the same frame.
    map.set_value(b, -10);
    field.update(&map, Some((b, b)), Some(WorldPoint::new(0.8, 0.0, 0.0)));
    assert_eq!(
        field.window().map(|w| w.0),
        Some(VoxelCoord::new(-32, -40, -40))
    );
    assert!(!field.covers(b));
    assert_eq!(field.nearest(edge), None);
}

//! The view's queries against the map they were written from: states, boxes, first hits,
//! scopes, dense and hashed indexes.

use super::*;
use voxmap_reader::snapshot::Pieces;

#[test]
fn view_agrees_with_the_map_on_every_query() {
    for seed in 1..4 {
        let map = random_map(seed, 3);
        let bytes = encode(&map, Scope::Whole, true);
        let view = SnapshotView::open_checked(&bytes).unwrap();
        // Written in many parallel pieces, checksum included.
        assert!(map.grid().leaf_count() > 10 * super::writer::OnPool.sizes().0);
        assert!(bytes.len() > 10 * 4096);
        let c = map.counts();
        assert_eq!(view.counts(), (c.occupied + c.free, c.occupied));
        assert_eq!((view.sequence(), view.timestamp_ns()), (42, 7));
        // Every known voxel, and random voxels around them.
        for (v, _) in map.grid().active_voxels() {
            assert_eq!(view.state(v), map.state(v));
            let (p, q) = (view.probability(v).unwrap(), map.probability(v).unwrap());
            assert!((p - q).abs() < 1e-12);
        }
        let mut rng = Rng(seed + 100);
        let mut voxels = Vec::new();
        for _ in 0..20000 {
            let v = VoxelCoord::new(rng.i(-70, 70), rng.i(-70, 70), rng.i(-70, 70));
            assert_eq!(view.state(v), map.state(v), "{v:?}");
            voxels.push(v);
        }
        // Batched, appended after what `out` held, staged (as for snapshots bigger than a
        // cache) or not; a length that leaves a short last group.
        for staged in [true, false] {
            let mut out = vec![VoxelState::Occupied];
            view.states_of(voxels[..19999].iter().map(|v| Some(*v)), staged, &mut out);
            assert_eq!(out.len(), 20000);
            assert_eq!(out[0], VoxelState::Occupied);
            for (v, s) in voxels.iter().zip(&out[1..]) {
                assert_eq!(*s, map.state(*v), "{v:?}");
            }
        }
        let tf = map.transform();
        let mut points: Vec<_> = voxels.iter().map(|&v| tf.voxel_center(v)).collect();
        points.extend([
            WorldPoint::new(f64::NAN, 0.0, 0.0),
            WorldPoint::new(1e300, 0.0, 0.0),
        ]);
        let (mut public, mut staged) = (Vec::new(), Vec::new());
        view.states_at(&points, &mut public);
        view.states_of(points.iter().map(|p| tf.voxel_of(p)), true, &mut staged);
        let known = public.iter().filter(|&&s| s != VoxelState::Unknown).count();
        assert!(known > 1000, "{known} known");
        assert_eq!(public, staged);
        // As codes into a byte buffer, staged (in groups, the last one short) and not.
        let codes: Vec<u8> = public.iter().map(|&s| s as u8).collect();
        let mut flat = vec![0u8; points.len()];
        let sink = &mut super::view::StateCodes(flat.iter_mut());
        view.states_of(points.iter().map(|p| tf.voxel_of(p)), true, sink);
        assert_eq!(flat, codes);
        let xyz: Vec<f64> = points.iter().flat_map(|p| [p.x, p.y, p.z]).collect();
        let mut flat = vec![9u8; points.len() + 1];
        view.state_codes_at(&xyz, &mut flat);
        assert_eq!((&flat[..points.len()], flat[points.len()]), (&codes[..], 9));
        for (p, s) in points.iter().zip(&public) {
            assert_eq!(*s, view.state_at(p), "{p:?}");
        }
        // Occupied iteration and bounds.
        let mut got: Vec<_> = view.occupied_voxels().collect();
        got.sort();
        let mut want: Vec<_> = map
            .grid()
            .active_voxels()
            .filter(|&(v, _)| map.state(v) == VoxelState::Occupied)
            .map(|(v, _)| v)
            .collect();
        want.sort();
        assert_eq!(got, want);
        let (lo, hi) = view.bounds().unwrap();
        for (v, _) in map.grid().active_voxels() {
            assert!(lo.min(v) == lo && hi.max(v) == hi);
        }
        // Line of sight against the map walked with the same DDA.
        for _ in 0..2000 {
            let a = WorldPoint::new(
                rng.f() * 8.0 - 4.0,
                rng.f() * 8.0 - 4.0,
                rng.f() * 8.0 - 4.0,
            );
            let b = WorldPoint::new(
                rng.f() * 8.0 - 4.0,
                rng.f() * 8.0 - 4.0,
                rng.f() * 8.0 - 4.0,
            );
            for unknown_blocks in [false, true] {
                let tf = map.transform();
                let want = find_voxel(tf.point_to_units(&a), tf.point_to_units(&b), |v| {
                    let s = map.state(v);
                    (s == VoxelState::Occupied || (unknown_blocks && s == VoxelState::Unknown))
                        .then_some(v)
                });
                assert_eq!(view.first_hit(&a, &b, unknown_blocks).unwrap(), want);
            }
        }
        // Box queries against brute force over voxel centres.
        for _ in 0..300 {
            let c = [
                rng.f() * 6.0 - 3.0,
                rng.f() * 6.0 - 3.0,
                rng.f() * 6.0 - 3.0,
            ];
            let h = [rng.f() * 0.6, rng.f() * 0.6, rng.f() * 0.6];
            let (min, max) = (
                WorldPoint::from([0, 1, 2].map(|k| c[k] - h[k])),
                WorldPoint::from([0, 1, 2].map(|k| c[k] + h[k])),
            );
            for unknown_is_free in [false, true] {
                let tf = map.transform();
                let (lo, hi) = (tf.voxel_of(&min).unwrap(), tf.voxel_of(&max).unwrap());
                let mut free = true;
                for x in lo.x..=hi.x {
                    for y in lo.y..=hi.y {
                        for z in lo.z..=hi.z {
                            // Every voxel the box overlaps, as OctoMap's bounding boxes.
                            match map.state(VoxelCoord::new(x, y, z)) {
                                VoxelState::Occupied => free = false,
                                VoxelState::Unknown if !unknown_is_free => free = false,
                                _ => {}
                            }
                        }
                    }
                }
                assert_eq!(
                    view.is_box_free(&min, &max, unknown_is_free),
                    Ok(free),
                    "{min:?} {max:?} {unknown_is_free}"
                );
            }
        }
    }
}

/// A voxel that reaches into the box by part of its width blocks it, though its centre is
/// outside (the OctoMap convention); bad boxes are errors, not answers.
#[test]
fn is_box_free_counts_every_voxel_the_box_overlaps() {
    let mut map = OccupancyMap::new(0.1, SensorModel::default()).unwrap();
    map.set_value(VoxelCoord::new(5, 0, 0), 100); // covers x in [0.5, 0.6)
    let bytes = encode(&map, Scope::Whole, false);
    let view = SnapshotView::open(&bytes).unwrap();
    let free = |lo: [f64; 3], hi: [f64; 3]| {
        view.is_box_free(&WorldPoint::from(lo), &WorldPoint::from(hi), true)
    };
    // Reaching 0.02 m into the voxel, 0.03 m short of its centre.
    assert_eq!(free([0.0, 0.0, 0.0], [0.52, 0.05, 0.05]), Ok(false));
    assert_eq!(free([0.58, 0.0, 0.0], [0.9, 0.05, 0.05]), Ok(false));
    // Stopping short of it; a box inside it, holding no voxel centre.
    assert_eq!(free([0.0, 0.0, 0.0], [0.49, 0.05, 0.05]), Ok(true));
    assert_eq!(free([0.51, 0.01, 0.01], [0.54, 0.04, 0.04]), Ok(false));
    // A degenerate box (a point) is the voxel holding it.
    assert_eq!(free([0.55, 0.05, 0.05], [0.55, 0.05, 0.05]), Ok(false));
    assert_eq!(
        free([0.6, 0.0, 0.0], [0.5, 0.1, 0.1]),
        Err(InvalidBox::Inverted)
    );
    assert_eq!(
        free([f64::NAN, 0.0, 0.0], [0.5, 0.1, 0.1]),
        Err(InvalidBox::OutsideIndexSpace)
    );
    assert_eq!(
        free([0.0, 0.0, 0.0], [1e12, 0.1, 0.1]),
        Err(InvalidBox::OutsideIndexSpace)
    );
}

/// Boxes with more leaves than the snapshot stores, unknown as free: answered by scanning
/// the stored leaves, which must agree with the map's occupied voxels.
#[test]
fn is_box_free_scans_stored_leaves_for_large_boxes() {
    let map = random_map(2, 1);
    let bytes = encode(&map, Scope::Whole, false);
    let view = SnapshotView::open(&bytes).unwrap();
    let tf = map.transform();
    let mut rng = Rng(31);
    let (mut free, mut blocked) = (0, 0);
    for _ in 0..200 {
        // 100 x 100 m slabs, 0.05-0.5 m thick, at random heights: 15,625 leaves or more.
        let z = rng.f() * 9.0 - 4.5;
        let (min, max) = (
            WorldPoint::new(-50.0, -50.0, z),
            WorldPoint::new(50.0, 50.0, z + 0.05 + rng.f() * 0.45),
        );
        assert!(view.leaf_count() < 125 * 125);
        let (lo, hi) = (tf.voxel_of(&min).unwrap(), tf.voxel_of(&max).unwrap());
        let want = map.grid().active_voxels().all(|(v, _)| {
            map.state(v) != VoxelState::Occupied
                || !(lo.x..=hi.x).contains(&v.x)
                || !(lo.y..=hi.y).contains(&v.y)
                || !(lo.z..=hi.z).contains(&v.z)
        });
        assert_eq!(
            view.is_box_free(&min, &max, true),
            Ok(want),
            "{min:?} {max:?}"
        );
        if want {
            free += 1;
        } else {
            blocked += 1;
        }
    }
    assert!(free > 5 && blocked > 5, "{free} free, {blocked} blocked");
}

/// `first_hit` passes leaves with nothing blocking whole (`raycast::LeafWalk`): check it on
/// long segments through a sparse map, from and to leaf corners, faces and edges (ties),
/// and along axes.
#[test]
fn first_hit_agrees_on_long_and_lattice_segments() {
    let map = random_map(9, 2);
    let bytes = encode(&map, Scope::Whole, false);
    let view = SnapshotView::open(&bytes).unwrap();
    let tf = map.transform();
    let mut rng = Rng(77);
    let lattice = |rng: &mut Rng| (rng.f() * 20.0).floor() * 0.4 - 4.0;
    for i in 0..6000 {
        let mut a = WorldPoint::new(lattice(&mut rng), lattice(&mut rng), lattice(&mut rng));
        let mut b = WorldPoint::new(lattice(&mut rng), lattice(&mut rng), lattice(&mut rng));
        match i % 3 {
            0 => b[i / 3 % 3] = a[i / 3 % 3],
            1 => {
                a += nalgebra::Vector3::new(rng.f(), rng.f(), rng.f()) * 0.05;
                b = WorldPoint::new(
                    rng.f() * 9.0 - 4.5,
                    rng.f() * 9.0 - 4.5,
                    rng.f() * 9.0 - 4.5,
                );
            }
            _ => {}
        }
        for unknown_blocks in [false, true] {
            let want = find_voxel(tf.point_to_units(&a), tf.point_to_units(&b), |v| {
                let s = map.state(v);
                (s == VoxelState::Occupied || (unknown_blocks && s == VoxelState::Unknown))
                    .then_some(v)
            });
            assert_eq!(
                view.first_hit(&a, &b, unknown_blocks).unwrap(),
                want,
                "{a:?} -> {b:?}, unknown blocks: {unknown_blocks}"
            );
        }
    }
}

#[test]
fn box_scope_keeps_exactly_the_voxels_inside() {
    let map = random_map(9, 2);
    // Across the origin (eight internal nodes), then within one node's corner.
    for (min, max) in [
        ([-1.0, -0.5, -0.3], [1.2, 0.7, 0.4]),
        ([0.05, 0.3, 0.0], [2.0, 3.9, 1.1]),
    ] {
        check_box_scope(&map, min, max);
    }
}

fn check_box_scope(map: &OccupancyMap, min: [f64; 3], max: [f64; 3]) {
    let bytes = encode(map, Scope::Box { min, max }, false);
    let whole = encode(map, Scope::Whole, false);
    assert!(bytes.len() < whole.len());
    let view = SnapshotView::open_checked(&bytes).unwrap();
    assert!(!view.has_values());
    let tf = map.transform();
    let mut inside = 0;
    for (v, _) in map.grid().active_voxels() {
        let c = tf.voxel_center(v);
        let is_in = (0..3).all(|k| min[k] <= c[k] && c[k] <= max[k]);
        inside += is_in as u32;
        assert_eq!(
            view.state(v),
            if is_in {
                map.state(v)
            } else {
                VoxelState::Unknown
            }
        );
        assert_eq!(view.probability(v), None);
    }
    assert!(inside > 1000);
}

/// A map whose blocks lie close together gets a dense index, one with far-apart parts a
/// hash table; both answer like the map.
#[test]
fn dense_and_hashed_indexes_answer_like_the_map() {
    let compact = random_map(11, 1);
    let mut spread = random_map(11, 1);
    let far = [[-50_000, 3, 9], [40_000, -70_000, 5], [8, 8, 90_000]];
    for (i, o) in far.iter().enumerate() {
        spread.set_value(VoxelCoord::from_array(*o), if i == 1 { 100 } else { -50 });
    }
    let tf = compact.transform();
    for (map, dense) in [(&compact, true), (&spread, false)] {
        let bytes = encode(map, Scope::Whole, false);
        let view = SnapshotView::open_checked(&bytes).unwrap();
        assert_eq!(view.header().flags & layout::FLAG_DENSE_INDEX != 0, dense);
        let mut rng = Rng(5);
        let mut voxels: Vec<VoxelCoord> = map.grid().active_voxels().map(|(v, _)| v).collect();
        voxels.extend((0..20_000).map(|_| {
            let mut c = || rng.i(-700, 700);
            VoxelCoord::new(c(), c(), c())
        }));
        for o in far {
            for d in [-65, -1, 0, 1, 64] {
                voxels.push(VoxelCoord::new(o[0] + d, o[1], o[2] - d));
            }
        }
        let mut batched = Vec::new();
        view.states_of(voxels.iter().map(|v| Some(*v)), true, &mut batched);
        for (v, b) in voxels.iter().zip(&batched) {
            assert_eq!(view.state(*v), map.state(*v), "{v:?}");
            assert_eq!(*b, map.state(*v), "{v:?}");
        }
        for _ in 0..2000 {
            let mut p = || {
                WorldPoint::new(
                    rng.f() * 12.0 - 6.0,
                    rng.f() * 12.0 - 6.0,
                    rng.f() * 12.0 - 6.0,
                )
            };
            let (a, b) = (p(), p());
            let want = find_voxel(tf.point_to_units(&a), tf.point_to_units(&b), |v| {
                (map.state(v) == VoxelState::Occupied).then_some(v)
            });
            assert_eq!(
                view.first_hit(&a, &b, false).unwrap(),
                want,
                "{a:?} -> {b:?}"
            );
        }
    }
    // A hash table needs more slots than blocks, so that probing ends.
    let mut bytes = encode(&spread, Scope::Whole, false);
    let mut h: Header = bytemuck::pod_read_unaligned(&bytes[..layout::HEADER_SIZE]);
    h.table_capacity = h.block_count;
    bytes[..layout::HEADER_SIZE].copy_from_slice(bytemuck::bytes_of(&h));
    assert_eq!(
        SnapshotView::open(&bytes).unwrap_err(),
        SnapshotError::BadHeader("table_capacity")
    );
}

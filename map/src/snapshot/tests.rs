use super::*;
use crate::coord::{VoxelCoord, WorldPoint};
use crate::model::VoxelState;
use crate::raycast::find_voxel;
use crate::test_rng::Rng;
use crate::{Frame, Integrator, IntegratorConfig, OccupancyMap, RayMode, SensorModel};
use nalgebra::{Isometry3, Translation3, UnitQuaternion};
use proptest::prelude::*;

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

#[test]
fn view_agrees_with_the_map_on_every_query() {
    for seed in 1..4 {
        let map = random_map(seed, 3);
        let bytes = encode(&map, Scope::Whole, true);
        let view = SnapshotView::open_checked(&bytes).unwrap();
        // Written in many parallel pieces, checksum included.
        assert!(map.grid().leaf_count() > 10 * super::writer::PIECE);
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

#[test]
fn empty_map_and_exact_buffer_sizes() {
    let map = OccupancyMap::new(0.2, SensorModel::default()).unwrap();
    let plan = Plan::new(&map, Scope::Whole, Meta::default());
    let bytes = plan.to_vec();
    assert_eq!(bytes.len(), plan.encoded_len());
    let view = SnapshotView::open_checked(&bytes).unwrap();
    assert_eq!(
        (view.leaf_count(), view.counts(), view.bounds()),
        (0, (0, 0), None)
    );
    assert_eq!(view.state(VoxelCoord::default()), VoxelState::Unknown);
    let (o, one) = (
        WorldPoint::new(0.0, 0.0, 0.0),
        WorldPoint::new(1.0, 1.0, 1.0),
    );
    assert_eq!(view.is_box_free(&o, &one, true), Ok(true));
    assert_eq!(view.is_box_free(&o, &one, false), Ok(false));
    // A box of 2^66 leaves: counted without overflow, answered from the stored leaves.
    let far = 0.1 * f64::from(1 << 29);
    assert_eq!(
        view.is_box_free(
            &WorldPoint::new(-far, -far, -far),
            &WorldPoint::new(far, far, far),
            true
        ),
        Ok(true)
    );
    let mut small = vec![0u8; plan.encoded_len() - 1];
    assert!(matches!(
        plan.write(&mut small),
        Err(EncodeError::BufferTooSmall { .. })
    ));
    // Writing into a larger, dirty buffer (a reused sample) gives the same bytes: every
    // byte is written, not assumed zero.
    let map = random_map(5, 1);
    for with_values in [false, true] {
        let meta = Meta {
            with_values,
            ..Meta::default()
        };
        let plan = Plan::new(&map, Scope::Whole, meta);
        let mut big = vec![0xAAu8; plan.encoded_len() + 100];
        let n = plan.write(&mut big).unwrap();
        assert_eq!(&big[..n], &plan.to_vec()[..]);
        assert_eq!(
            SnapshotView::open_checked(&big).unwrap().as_bytes().len(),
            n
        );
    }
}

#[test]
fn corrupt_bytes_get_clear_errors() {
    let map = random_map(3, 1);
    let good = encode(&map, Scope::Whole, true);
    let h = *SnapshotView::open(&good).unwrap().header();
    let with = |f: &dyn Fn(&mut Header)| {
        let mut b = good.clone();
        let mut hh = h;
        f(&mut hh);
        b[..layout::HEADER_SIZE].copy_from_slice(bytemuck::bytes_of(&hh));
        b
    };
    assert_eq!(
        SnapshotView::open(&good[..10]).unwrap_err(),
        SnapshotError::Truncated {
            needed: layout::HEADER_SIZE as u64,
            got: 10
        }
    );
    assert!(matches!(
        SnapshotView::open(&good[..good.len() - 1]),
        Err(SnapshotError::Truncated { .. })
    ));
    assert_eq!(
        SnapshotView::open(&with(&|h| h.magic[0] = b'X')).unwrap_err(),
        SnapshotError::BadMagic
    );
    assert_eq!(
        SnapshotView::open(&with(&|h| h.version = 9)).unwrap_err(),
        SnapshotError::UnsupportedVersion(9)
    );
    assert_eq!(
        SnapshotView::open(&with(&|h| h.resolution = f64::NAN)).unwrap_err(),
        SnapshotError::BadHeader("resolution")
    );
    assert_eq!(
        SnapshotView::open(&with(&|h| h.masks_offset += 8 * 1_000_000)).unwrap_err(),
        SnapshotError::SectionOutOfBounds("masks")
    );
    assert_eq!(
        SnapshotView::open(&with(&|h| h.leaves_offset = u64::MAX - 3)).unwrap_err(),
        SnapshotError::SectionOutOfBounds("leaves")
    );
    assert_eq!(
        SnapshotView::open(&with(&|h| h.leaf_count = u64::MAX)).unwrap_err(),
        SnapshotError::BadHeader("leaf_count")
    );
    assert_eq!(
        SnapshotView::open(&with(&|h| h.block_count = h.leaf_count + 1)).unwrap_err(),
        SnapshotError::BadHeader("block_count")
    );
    // The test map's blocks fill a dense index; its size must match the table's.
    assert_ne!(h.flags & layout::FLAG_DENSE_INDEX, 0);
    assert_eq!(
        SnapshotView::open(&with(&|h| h.table_capacity += 1)).unwrap_err(),
        SnapshotError::BadHeader("index_dims")
    );
    assert_eq!(
        SnapshotView::open(&with(&|h| h.flags &= !layout::FLAG_DENSE_INDEX)).unwrap_err(),
        SnapshotError::BadHeader("index fields of a hash table")
    );
    assert_eq!(
        SnapshotView::open(&with(&|h| h.blocks_offset = h.total_len)).unwrap_err(),
        SnapshotError::SectionOutOfBounds("blocks")
    );
    let bad_record = SnapshotError::BadIndex("leaf mask kinds or record malformed");
    assert_eq!(
        SnapshotView::open(&with(&|h| h.masks_len -= 1)).unwrap_err(),
        bad_record
    );
    // A leaf entry whose record offset points past the masks section.
    let mut b = good.clone();
    let at = h.leaves_offset as usize;
    b[at..at + 4].copy_from_slice(&(u32::MAX - 4).to_le_bytes());
    assert_eq!(SnapshotView::open(&b).unwrap_err(), bad_record);
    // An entry whose occupied kind names no encoding (6), and one with a reserved byte set.
    let mut b = good.clone();
    b[at + 5] = 6;
    assert_eq!(SnapshotView::open(&b).unwrap_err(), bad_record);
    let mut b = good.clone();
    b[at + 6] = 1;
    assert_eq!(
        SnapshotView::open(&b).unwrap_err(),
        SnapshotError::BadIndex("leaf entry reserved bytes set")
    );
    // Blocks: a table slot naming no block, an origin off the 64-voxel lattice, a block
    // whose leaves overlap its neighbour's, and blocks one leaf short.
    assert!(h.block_count >= 2, "the test map spans several blocks");
    let mut b = good.clone();
    let slots = h.table_offset as usize..(h.table_offset + 4 * h.table_capacity) as usize;
    let used: Vec<usize> = slots
        .step_by(4)
        .filter(|&s| b[s..s + 4] != [0; 4])
        .collect();
    b[used[0]..used[0] + 4].copy_from_slice(&(h.block_count as u32 + 1).to_le_bytes());
    assert_eq!(
        SnapshotView::open(&b).unwrap_err(),
        SnapshotError::BadIndex("table entry beyond block_count")
    );
    // Two blocks swapped in the dense index: each slot names a block elsewhere.
    let mut b = good.clone();
    let (s0, s1) = (used[0], used[1]);
    let (e0, e1) = (b[s0..s0 + 4].to_vec(), b[s1..s1 + 4].to_vec());
    b[s0..s0 + 4].copy_from_slice(&e1);
    b[s1..s1 + 4].copy_from_slice(&e0);
    assert_eq!(
        SnapshotView::open(&b).unwrap_err(),
        SnapshotError::BadIndex("dense index slot names another block")
    );
    let block = |i: u64| (h.blocks_offset + layout::BLOCK_SIZE as u64 * i) as usize;
    let mut b = good.clone();
    b[block(1) + 8] ^= 32;
    assert_eq!(
        SnapshotView::open(&b).unwrap_err(),
        SnapshotError::BadIndex("block origin not a multiple of 64")
    );
    let mut b = good.clone();
    b[block(1) + 12] = b[block(1) + 12].wrapping_sub(1);
    assert_eq!(
        SnapshotView::open(&b).unwrap_err(),
        SnapshotError::BadIndex("blocks' leaves out of sequence")
    );
    let mut b = good.clone();
    b[block(0) + layout::BLOCK_RANKS_AT + 2] ^= 1;
    assert_eq!(
        SnapshotView::open(&b).unwrap_err(),
        SnapshotError::BadIndex("block rank miscounts its leaves")
    );
    // The last block one leaf short, its ranks recounted.
    let last = block(h.block_count - 1);
    let mut b = good.clone();
    let bits = last + layout::BLOCK_LEAVES_AT;
    let w = (bits..bits + 64).rev().find(|&i| b[i] != 0).unwrap();
    b[w] &= b[w] - 1; // clear its lowest set bit
    let word = |b: &[u8], k: usize| u64::from_le_bytes(b[bits + 8 * k..][..8].try_into().unwrap());
    let mut below = 0u16;
    for k in 0..8 {
        let at = last + layout::BLOCK_RANKS_AT + 2 * k;
        b[at..at + 2].copy_from_slice(&below.to_le_bytes());
        below += word(&b, k).count_ones() as u16;
    }
    assert_eq!(
        SnapshotView::open(&b).unwrap_err(),
        SnapshotError::BadIndex("blocks do not hold leaf_count leaves")
    );
    let mut flipped = good.clone();
    let last = flipped.len() - 1;
    flipped[last] ^= 1;
    assert!(
        SnapshotView::open(&flipped).is_ok(),
        "structure still valid"
    );
    assert!(matches!(
        SnapshotView::open_checked(&flipped),
        Err(SnapshotError::ChecksumMismatch { .. })
    ));
    let msg = SnapshotError::UnsupportedVersion(9).to_string();
    assert!(msg.contains("version 9"), "{msg}");
}

#[test]
fn leaves_store_only_the_masks_they_need() {
    let mut map = OccupancyMap::new(0.1, SensorModel::default()).unwrap();
    let q = *map.quantized();
    // A fully known free leaf, a fully known leaf with one occupied voxel, a partly known
    // free leaf and a partly known leaf with an occupied voxel.
    for i in 0..512 {
        let v = crate::grid::voxel_at(VoxelCoord::new(0, 0, 0), i);
        map.set_value(v, q.min);
        map.set_value(v + VoxelCoord::new(8, 0, 0), q.min);
    }
    map.set_value(VoxelCoord::new(9, 1, 1), q.max);
    map.set_value(VoxelCoord::new(16, 0, 0), q.min);
    map.set_value(VoxelCoord::new(24, 0, 0), q.max);
    let bytes = encode(&map, Scope::Whole, false);
    let view = SnapshotView::open_checked(&bytes).unwrap();
    // Records: empty; one occupied row (a presence word and a byte); one known row; a
    // known and an occupied row.
    assert_eq!(view.header().masks_len, 9 + 9 + 18);
    assert_eq!(view.counts(), (512 + 512 + 2, 2));
    for (v, s) in [
        (VoxelCoord::new(3, 4, 5), VoxelState::Free),
        (VoxelCoord::new(9, 1, 1), VoxelState::Occupied),
        (VoxelCoord::new(10, 1, 1), VoxelState::Free),
        (VoxelCoord::new(16, 0, 0), VoxelState::Free),
        (VoxelCoord::new(17, 0, 0), VoxelState::Unknown),
        (VoxelCoord::new(24, 0, 0), VoxelState::Occupied),
        (VoxelCoord::new(25, 0, 0), VoxelState::Unknown),
    ] {
        assert_eq!((v, view.state(v)), (v, s));
        assert_eq!(map.state(v), s);
    }
    let occ: Vec<_> = view.occupied_voxels().collect();
    assert_eq!(
        occ,
        vec![VoxelCoord::new(9, 1, 1), VoxelCoord::new(24, 0, 0)]
    );
}

/// Every query on whatever `open` accepts: must not panic.
fn exercise(bytes: &[u8]) {
    if let Ok(v) = SnapshotView::open(bytes) {
        let _ = SnapshotView::open_checked(bytes);
        let voxels: Vec<_> = (-20..20)
            .map(|x| VoxelCoord::new(x * 3, -x, x * 7))
            .collect();
        let mut batched = Vec::new();
        v.states(&voxels, &mut batched);
        v.states_of(voxels.iter().map(|v| Some(*v)), true, &mut batched);
        assert_eq!(batched.len(), 2 * voxels.len());
        for (i, p) in voxels.iter().enumerate() {
            assert_eq!(v.state(*p), batched[i]);
            assert_eq!(v.state(*p), batched[voxels.len() + i]);
            let _ = v.probability(*p);
        }
        let _ = v.first_hit(
            &WorldPoint::new(-3.0, -2.0, -1.0),
            &WorldPoint::new(3.0, 2.0, 1.0),
            true,
        );
        let _ = v.first_hit(
            &WorldPoint::new(f64::NAN, 0.0, 0.0),
            &WorldPoint::new(3.0, 2.0, 1.0),
            true,
        );
        let _ = v.is_box_free(
            &WorldPoint::new(-1.0, -1.0, -1.0),
            &WorldPoint::new(1.0, 1.0, 1.0),
            false,
        );
        let _ = v.is_box_free(
            &WorldPoint::new(-1e6, -1e6, -1e6),
            &WorldPoint::new(1e6, 1e6, 1e6),
            true,
        );
        let _ = v.occupied_voxels().take(100_000).count();
        let _ = (v.bounds(), v.counts(), v.header());
        if let Some(f) = v.distance_field() {
            let points: Vec<WorldPoint> = (-30..30)
                .map(|i| {
                    WorldPoint::new(
                        0.11 * f64::from(i),
                        -0.07 * f64::from(i),
                        0.05 * f64::from(i),
                    )
                })
                .chain([
                    WorldPoint::new(f64::NAN, 0.0, 0.0),
                    WorldPoint::new(1e12, 0.0, 0.0),
                ])
                .collect();
            let (mut d, mut g, mut n) = (Vec::new(), Vec::new(), Vec::new());
            f.distances_at(&points, &mut d);
            f.distances_and_gradients_at(&points, &mut g);
            f.nearest_obstacles(&points, &mut n);
            for p in &voxels {
                let _ = f.distance(*p);
            }
            let _ = (f.window(), f.band_voxels(), f.max_distance());
        }
    }
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 300, ..ProptestConfig::default() })]

    #[test]
    fn arbitrary_bytes_never_panic(bytes in proptest::collection::vec(any::<u8>(), 0..2048)) {
        exercise(&bytes);
    }

    /// Arbitrary sections behind a valid header, so that they get past the magic, version
    /// and size checks: mostly zero bytes (30 to 1), so that about one case in six still
    /// validates and the queries run on garbage.
    #[test]
    fn arbitrary_sections_never_panic(
        body in proptest::collection::vec(prop_oneof![30 => Just(0u8), 1 => any::<u8>()], 1..4096)
    ) {
        thread_local!(static SMALL: Vec<u8> = {
            let mut map = OccupancyMap::new(0.1, SensorModel::default()).unwrap();
            for (i, v) in [(0, 90i8), (7, -40), (100, 20), (-9, 60), (513, -3)] {
                map.set_value(VoxelCoord::new(i, i / 3, -i), v);
            }
            encode(&map, Scope::Whole, true)
        });
        let mut b = SMALL.with(|s| s.clone());
        for (d, s) in b[layout::HEADER_SIZE..].iter_mut().zip(body.iter().cycle()) {
            *d = *s;
        }
        exercise(&b);
    }

    /// Flips and cuts mostly inside the distance field section.
    #[test]
    fn mutated_field_sections_never_panic(flips in proptest::collection::vec((any::<usize>(), any::<u8>()), 1..8), cut in any::<usize>()) {
        thread_local!(static GOOD: (Vec<u8>, usize) = {
            let map = random_map(5, 1);
            let bytes = with_field(&map, Scope::Whole, crate::field::UnknownPolicy::Free);
            let start = bytes.len() - field_section_len(&bytes);
            (bytes, start)
        });
        let (mut b, start) = GOOD.with(|g| g.clone());
        for (at, x) in flips {
            let i = if at % 4 != 0 { start + at % (b.len() - start) } else { at % b.len() };
            b[i] ^= x;
        }
        if cut % 4 == 0 {
            b.truncate(cut % (b.len() + 1));
        }
        exercise(&b);
    }

    #[test]
    fn mutated_snapshots_never_panic(flips in proptest::collection::vec((any::<usize>(), any::<u8>()), 1..8), cut in any::<usize>(), hashed in any::<bool>()) {
        // A dense index, and a hash table (one far leaf spreads the blocks).
        thread_local!(static GOOD: [Vec<u8>; 2] = {
            let mut map = random_map(4, 1);
            let dense = encode(&map, Scope::Whole, true);
            map.set_value(VoxelCoord::new(30_000, -7, 2), 90);
            [dense, encode(&map, Scope::Whole, true)]
        });
        let mut b = GOOD.with(|g| g[usize::from(hashed)].clone());
        for (at, x) in flips {
            // Bias half the flips into the header, where the offsets live.
            let i = if at % 2 == 0 { at % layout::HEADER_SIZE } else { at % b.len() };
            b[i] ^= x;
        }
        if cut % 4 == 0 {
            b.truncate(cut % (b.len() + 1));
        }
        exercise(&b);
    }
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

#[test]
fn leaves_with_nothing_known_are_left_out() {
    let mut map = random_map(7, 1);
    let before = encode(&map, Scope::Whole, true);
    // Empty leaves far from the map's: before, amid and after its leaves in block order.
    for o in [[-4096, -4096, -4096], [4096, -4096, 0], [4096, 4096, 4096]] {
        map.grid_mut()
            .leaf_index_or_insert(VoxelCoord::from_array(o), None);
    }
    let after = encode(&map, Scope::Whole, true);
    let (a, b) = (
        SnapshotView::open_checked(&before).unwrap(),
        SnapshotView::open_checked(&after).unwrap(),
    );
    assert_eq!(a.leaf_count(), b.leaf_count());
    assert_eq!(a.counts(), b.counts());
    assert_eq!(before, after);
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

/// Every voxel of every leaf (and around them): the snapshot's field answers what the
/// field kept, under both policies, whole and in a box; interpolation between centres
/// passes through each centre's value, and its gradient points away from an obstacle.
#[test]
fn field_section_answers_like_the_field() {
    use crate::field::{DistanceField, FieldConfig, UnknownPolicy};
    let map = random_map(21, 2);
    for unknown in [UnknownPolicy::Free, UnknownPolicy::Occupied] {
        let cfg = FieldConfig {
            max_distance: 0.5,
            unknown,
            window: None,
        };
        let mut field = DistanceField::new(cfg, 0.1).unwrap();
        field.rebuild(&map, None);
        let bytes = Plan::new(&map, Scope::Whole, Meta::default())
            .with_field(&field)
            .to_vec();
        let view = SnapshotView::open_checked(&bytes).unwrap();
        let f = view.distance_field().expect("a field");
        assert_eq!(f.band_voxels(), field.band_voxels());
        assert_eq!((f.radius(), f.unknown()), (5, unknown));
        // 254 / 5 steps a voxel: the interpolating queries' distances, to the nearest step.
        assert!((f.step() - 0.1 / 50.0).abs() < 1e-15, "{}", f.step());
        let quantised = |d: f64| ((d / f.step()).round() * f.step()).min(f.max_distance());
        let (mut checked, mut interpolated) = (0, 0);
        for (origin, _) in map.grid().leaves() {
            for i in (0..512).step_by(3) {
                let v = crate::tree::voxel_at(origin, i);
                let want = field.distance(v).unwrap_or(0.5);
                assert_eq!(f.distance(v), Some(want), "{v:?}");
                let c = map.transform().voxel_center(v);
                // None where a neighbour of the interpolation is unknown (map edges); at a
                // centre, the voxel's distance to the nearest step.
                if let Some(at) = f.distance_at(&c) {
                    assert!((at - quantised(want)).abs() < 1e-9, "{v:?}: {at} vs {want}");
                    assert!((at - want).abs() <= f.step() / 2.0 + 1e-9);
                    interpolated += 1;
                }
                match (f.nearest_obstacle(&c), field.nearest(v)) {
                    (
                        Nearest::At {
                            voxel, distance, ..
                        },
                        Some(o),
                    ) => {
                        assert_eq!(
                            voxel,
                            v + VoxelCoord::new(o[0].into(), o[1].into(), o[2].into())
                        );
                        assert!((distance - want).abs() < 1e-12);
                    }
                    (Nearest::NoneWithin, None) => {}
                    (got, want) => panic!("{v:?}: {got:?} vs {want:?}"),
                }
                checked += 1;
            }
        }
        assert!(
            checked > 10_000 && interpolated > checked / 2,
            "{interpolated} of {checked}"
        );
        // Between centres: the trilinear blend of the eight voxels' distances, whether
        // they lie in one leaf or straddle two to eight.
        let origins: Vec<VoxelCoord> = map.grid().leaves().map(|(o, _)| o).collect();
        let mut rng = Rng(5);
        let (mut straddling, mut blended) = (0, 0);
        for _ in 0..20_000 {
            let o = origins[rng.i(0, origins.len() as i32 - 1) as usize];
            let u = [0, 1, 2].map(|k| f64::from(o.to_array()[k]) + 8.0 * rng.f());
            let p = WorldPoint::new(0.1 * u[0], 0.1 * u[1], 0.1 * u[2]);
            let g = [0, 1, 2].map(|k| u[k] - 0.5);
            let b = VoxelCoord::new(
                g[0].floor() as i32,
                g[1].floor() as i32,
                g[2].floor() as i32,
            );
            let t = [0, 1, 2].map(|k| g[k] - g[k].floor());
            let corner = |k: i32| {
                f.distance(b + VoxelCoord::new(k & 1, k >> 1 & 1, k >> 2))
                    .map(quantised)
            };
            let want = (0..8).try_fold(0.0, |acc, k| {
                let w = [0, 1, 2].map(|a| if k >> a & 1 == 1 { t[a] } else { 1.0 - t[a] });
                Some(acc + corner(k)? * w[0] * w[1] * w[2])
            });
            let got = f.distance_at(&p);
            match (got, want) {
                (Some(g), Some(w)) => assert!((g - w).abs() < 1e-9, "{p:?}: {g} vs {w}"),
                (None, None) => {}
                _ => panic!("{p:?}: {got:?} vs {want:?}"),
            }
            blended += usize::from(got.is_some());
            straddling += usize::from(b.to_array().iter().any(|c| c & 7 == 7));
        }
        assert!(
            blended > 10_000 && straddling > 3_000,
            "{blended}, {straddling}"
        );
        // Outside every leaf: unknown under `free`, an obstacle under `occupied`.
        let far = VoxelCoord::new(5000, 5000, 5000);
        let want = (unknown == UnknownPolicy::Occupied).then_some(0.0);
        assert_eq!(f.distance(far), want);
    }
    // No field: none.
    let plain = encode(&map, Scope::Whole, false);
    assert!(SnapshotView::open(&plain)
        .unwrap()
        .distance_field()
        .is_none());
}

#[test]
fn field_gradient_points_away_from_the_obstacle() {
    use crate::field::{DistanceField, FieldConfig};
    let mut map = OccupancyMap::new(0.1, SensorModel::default()).unwrap();
    for z in -12..12 {
        for y in -12..12 {
            for x in -12..12 {
                map.set_value(VoxelCoord::new(x, y, z), -50);
            }
        }
    }
    map.set_value(VoxelCoord::new(0, 0, 0), 100);
    let mut field = DistanceField::new(
        FieldConfig {
            max_distance: 1.0,
            ..Default::default()
        },
        0.1,
    )
    .unwrap();
    field.rebuild(&map, None);
    let bytes = Plan::new(&map, Scope::Whole, Meta::default())
        .with_field(&field)
        .to_vec();
    let view = SnapshotView::open(&bytes).unwrap();
    let f = view.distance_field().unwrap();
    let mut rng = Rng(2);
    for _ in 0..500 {
        let dir = nalgebra::Vector3::new(rng.f() - 0.5, rng.f() - 0.5, rng.f() - 0.5).normalize();
        let r = 0.25 + 0.5 * rng.f();
        let p = WorldPoint::new(0.05, 0.05, 0.05) + dir * r;
        let (d, g) = f.distance_and_gradient_at(&p).unwrap();
        // Trilinear over exact centre distances: within half a voxel's diagonal.
        assert!((d - r).abs() < 0.05, "{p:?}: {d} vs {r}");
        assert!(
            g.dot(&dir) > 0.7 * g.norm() && (g.norm() - 1.0).abs() < 0.3,
            "{p:?}: {g:?}"
        );
        let h = 1e-4;
        let fd = (f
            .distance_at(&(p + nalgebra::Vector3::new(h, 0.0, 0.0)))
            .unwrap()
            - f.distance_at(&(p - nalgebra::Vector3::new(h, 0.0, 0.0)))
                .unwrap())
            / (2.0 * h);
        assert!(
            (fd - g.x).abs() < 1e-3 || (fd - g.x).abs() < 0.2 * g.norm(),
            "{fd} vs {}",
            g.x
        );
    }
    // Beyond the max distance: the max, flat.
    let (d, g) = f
        .distance_and_gradient_at(&WorldPoint::new(1.15, 0.55, -0.45))
        .unwrap();
    assert_eq!((d, g.norm()), (1.0, 0.0));
}

#[test]
fn a_box_scope_limits_the_field_to_the_box() {
    let map = random_map(23, 1);
    let scope = Scope::Box {
        min: [-1.0, -1.0, -1.0],
        max: [1.0, 1.0, 1.0],
    };
    let bytes = with_field(&map, scope, crate::field::UnknownPolicy::Occupied);
    let view = SnapshotView::open_checked(&bytes).unwrap();
    let f = view.distance_field().unwrap();
    assert_eq!(
        f.window(),
        (VoxelCoord::new(-10, -10, -10), VoxelCoord::new(9, 9, 9))
    );
    assert_eq!(f.distance(VoxelCoord::new(10, 0, 0)), None);
    assert!(f.distance(VoxelCoord::new(9, 0, 0)).is_some());
    assert_eq!(
        f.distance_at(&WorldPoint::new(0.99, 0.0, 0.0)),
        None,
        "a corner is outside"
    );
}

/// The field section as the format describes it: per block, its band leaves and where
/// their distance blocks start; the distance blocks on 64-byte lines of the snapshot,
/// each voxel's distance in steps (Morton order, 255 outside the band); the offsets after
/// them; and every lie about its layout refused by name.
#[test]
fn field_section_layout_and_its_errors() {
    use layout::*;
    let map = random_map(9, 1);
    let cfg = crate::field::FieldConfig {
        max_distance: 0.7,
        ..Default::default()
    };
    let mut field = crate::field::DistanceField::new(cfg, 0.1).unwrap();
    field.rebuild(&map, None);
    let good = Plan::new(&map, Scope::Whole, Meta::default())
        .with_field(&field)
        .to_vec();
    let view = SnapshotView::open_checked(&good).unwrap();
    let (n, nb) = (view.header().leaf_count, view.header().block_count);
    let at = good.len() - field_section_len(&good);
    let h: FieldHeader = bytemuck::pod_read_unaligned(&good[at..at + FIELD_HEADER_SIZE]);
    assert_eq!((h.radius, h.steps), (7, 36));
    let dists_at = field_dists_at(at as u64, nb, n) as usize;
    assert_eq!(dists_at % 64, 0);
    let data_at = dists_at + FIELD_DISTS * h.dist_blocks as usize;
    assert_eq!(data_at + h.data_len as usize, good.len());
    let block_at = |i: usize| at + FIELD_HEADER_SIZE + FIELD_BLOCK_SIZE * i;
    let entry_at = |i: usize| block_at(nb as usize) + FIELD_ENTRY_SIZE * i;
    let entry =
        |i: usize| -> FieldEntry { bytemuck::pod_read_unaligned(&good[entry_at(i)..][..4]) };
    let (mut blocks, mut near) = (0u32, 0);
    let mut band_leaves = std::collections::HashMap::new();
    for (i, (origin, _)) in view.stored_leaves().enumerate() {
        let e = entry(i);
        let Some(band) = field.leaf(origin) else {
            assert_eq!(e, FieldEntry::NONE);
            continue;
        };
        // A leaf whole in the band is not masked; distance blocks come in leaf order.
        assert_eq!(e.masked(), band.mask().count() < 512);
        band_leaves.insert(origin, blocks);
        let dists = &good[dists_at + FIELD_DISTS * blocks as usize..][..FIELD_DISTS];
        blocks += 1;
        for (m, &q) in dists.iter().enumerate() {
            let v = crate::tree::voxel_at(origin, usize::from(crate::tree::UNMORTON[m]));
            match field.nearest(v) {
                Some(o) => {
                    let exact = f64::from(crate::field::offset_len2(o)).sqrt() * 36.0;
                    assert!((f64::from(q) - exact).abs() <= 0.5, "{v:?}: {q} vs {exact}");
                    near += 1;
                }
                None => assert_eq!(q, FIELD_DIST_FAR, "{v:?}"),
            }
        }
    }
    assert_eq!(u64::from(blocks), h.dist_blocks);
    assert!(
        blocks > 20 && near as u64 == field.band_voxels(),
        "{blocks} {near}"
    );
    // Each block's first distance block and band bits name the same leaves.
    let snapshot_blocks: &[BlockEntry] = bytemuck::cast_slice(
        &good[view.header().blocks_offset as usize..][..BLOCK_SIZE * nb as usize],
    );
    for (i, b) in snapshot_blocks.iter().enumerate() {
        let fb: FieldBlock = bytemuck::pod_read_unaligned(&good[block_at(i)..][..FIELD_BLOCK_SIZE]);
        let mut k = 0;
        for j in 0..512 {
            let leaf = VoxelCoord::from_array(b.origin)
                + VoxelCoord::new(8 * (j & 7), 8 * (j >> 3 & 7), 8 * (j >> 6));
            let set = fb.band[j as usize / 64] >> (j % 64) & 1 == 1;
            assert_eq!(set, band_leaves.contains_key(&leaf), "{leaf:?}");
            if set {
                assert_eq!(band_leaves[&leaf], fb.first + k);
                k += 1;
            }
        }
    }
    let open = |b: &[u8]| SnapshotView::open(b).map(|_| ()).unwrap_err();
    let header = |f: &dyn Fn(&mut FieldHeader)| {
        let mut b = good.clone();
        let mut hh = h;
        f(&mut hh);
        b[at..at + FIELD_HEADER_SIZE].copy_from_slice(bytemuck::bytes_of(&hh));
        open(&b)
    };
    assert_eq!(
        header(&|h| h.steps += 1),
        SnapshotError::BadHeader("field steps")
    );
    assert_eq!(
        header(&|h| h.data_len -= 4),
        SnapshotError::BadHeader("field lengths")
    );
    assert_eq!(
        header(&|h| h.dist_blocks = n + 1),
        SnapshotError::BadHeader("field lengths")
    );
    assert_eq!(
        header(&|h| h.data_len -= 8),
        SnapshotError::SectionOutOfBounds("field")
    );
    assert_eq!(
        header(&|h| h.dist_blocks -= 1),
        SnapshotError::SectionOutOfBounds("field")
    );
    let pad = entry_at(n as usize);
    if pad < dists_at {
        let mut b = good.clone();
        b[pad] = 1;
        assert_eq!(open(&b), SnapshotError::BadHeader("field padding"));
    }
    let mut b = good.clone();
    b[block_at(nb as usize - 1)] ^= 1;
    assert_eq!(
        open(&b),
        SnapshotError::BadIndex("field block out of sequence")
    );
    let with_entry = |i: usize, e: FieldEntry| {
        let mut b = good.clone();
        b[entry_at(i)..][..4].copy_from_slice(bytemuck::bytes_of(&e));
        open(&b)
    };
    let last = (0..n as usize)
        .rev()
        .find(|&i| entry(i) != FieldEntry::NONE)
        .unwrap();
    assert_eq!(
        with_entry(
            last,
            FieldEntry {
                data: (h.data_len / 8) as u32
            }
        ),
        SnapshotError::BadIndex("field leaf data outside the section")
    );
    assert_eq!(
        with_entry(last, FieldEntry::NONE),
        SnapshotError::BadIndex("field band leaf without data")
    );
}

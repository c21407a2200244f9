//! The snapshot's bytes: sizes, what each leaf stores, and corrupt or mutated bytes that
//! must be refused by name or answered without a panic.

use super::*;

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

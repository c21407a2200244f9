//! The distance field section: answers like the field it was written from, its gradient,
//! a box scope, and its layout and errors.

use super::*;

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

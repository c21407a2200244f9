//! The grid's tests: lookups across signs and nodes, group insertion, block order,
//! removal of nodes, parallel updates.
use super::*;

#[test]
fn set_get_across_signs_and_nodes() {
    let mut g = Grid::<i8>::new();
    let pts = [
        VoxelCoord::new(0, 0, 0),
        VoxelCoord::new(-1, -1, -1),
        VoxelCoord::new(7, 8, -8),
        VoxelCoord::new(127, 128, -129),
        VoxelCoord::new(i32::MAX >> 2, i32::MIN >> 2, 5),
    ];
    for (i, &p) in pts.iter().enumerate() {
        g.set(p, i as i8 + 1);
    }
    for (i, &p) in pts.iter().enumerate() {
        assert_eq!(g.get(p), Some(i as i8 + 1), "{p:?}");
        assert_eq!(g.accessor().get(p), Some(i as i8 + 1));
    }
    assert_eq!(g.get(VoxelCoord::new(1, 0, 0)), None);
    assert_eq!(g.leaf_count(), 5);
    let mut got: Vec<_> = g.active_voxels().collect();
    got.sort();
    let mut want: Vec<_> = pts
        .iter()
        .enumerate()
        .map(|(i, &p)| (p, i as i8 + 1))
        .collect();
    want.sort();
    assert_eq!(got, want);
}

#[test]
fn leaf_box_masks_hold_the_voxels_inside() {
    let mut rng = crate::test_rng::Rng(3);
    for _ in 0..2000 {
        let o = VoxelCoord::new(rng.i(-40, 40), rng.i(-40, 40), rng.i(-40, 40))
            .shr(3)
            .shl(3);
        let mut c = || rng.i(-50, 50);
        let (a, b) = (
            VoxelCoord::new(c(), c(), c()),
            VoxelCoord::new(c(), c(), c()),
        );
        let (lo, hi) = (
            VoxelCoord::new(a.x.min(b.x), a.y.min(b.y), a.z.min(b.z)),
            VoxelCoord::new(a.x.max(b.x), a.y.max(b.y), a.z.max(b.z)),
        );
        let m = leaf_box_mask(o, lo, hi);
        for i in 0..LEAF_VOXELS {
            let v = voxel_at(o, i);
            let inside = (0..3).all(|k| {
                lo.to_array()[k] <= v.to_array()[k] && v.to_array()[k] <= hi.to_array()[k]
            });
            assert_eq!(m.get(i), inside, "{o:?} [{lo:?}, {hi:?}] {v:?}");
        }
    }
    let (near, far) = (
        VoxelCoord::new(i32::MIN, i32::MIN, i32::MIN),
        VoxelCoord::new(i32::MAX, i32::MAX, i32::MAX),
    );
    assert_eq!(
        leaf_box_mask(VoxelCoord::new(-8, 0, 0), near, far),
        crate::mask::Mask512::FULL
    );
}

#[test]
fn leaves_inserted_by_groups_are_those_inserted_one_by_one() {
    let mut rng = crate::test_rng::Rng(11);
    let mut leaf = || {
        VoxelCoord::new(rng.i(-300, 300), rng.i(-300, 300), rng.i(-40, 40))
            .shr(LEAF_LOG2)
            .shl(LEAF_LOG2)
    };
    let before: Vec<VoxelCoord> = (0..300).map(|_| leaf()).collect();
    let mut origins: Vec<VoxelCoord> = (0..4000).map(|_| leaf()).collect();
    let node = |o: &VoxelCoord| {
        let k = internal_key(*o);
        (k.z, k.y, k.x)
    };
    origins.sort_by_key(|o| (node(o), o.z, o.y, o.x));
    origins.dedup();
    // Grouped by internal node, in a scrambled order of nodes, one group empty.
    let mut groups: Vec<Vec<(VoxelCoord, usize)>> = Vec::new();
    for (i, &o) in origins.iter().enumerate() {
        match groups.last_mut() {
            Some(g) if internal_key(g[0].0) == internal_key(o) => g.push((o, i)),
            _ => groups.push(vec![(o, i)]),
        }
    }
    groups.reverse();
    groups.swap(0, 3);
    let as_nodes = |groups: &[Vec<(VoxelCoord, usize)>]| -> Vec<NodeLeaves<usize>> {
        (groups.iter())
            .map(|g| {
                let node = internal_key(g[0].0).shl(INTERNAL_TOTAL_LOG2);
                let children = g.iter().map(|&(o, i)| (child_index(o) as u16, i));
                let children: Vec<_> = children.collect();
                for (&(o, _), &(c, _)) in g.iter().zip(&children) {
                    assert_eq!(child_origin(node, c), o);
                }
                NodeLeaves { node, children }
            })
            .collect()
    };
    let mut nodes = as_nodes(&groups);
    let empty = NodeLeaves {
        node: VoxelCoord::new(128, 0, -256),
        children: Vec::new(),
    };
    nodes.insert(2, empty);
    // Two groups in one node: the one-by-one path.
    let mut shared = nodes.clone();
    let half = shared[1].children.len() / 2;
    let tail = shared[1].children.split_off(half);
    shared.push(NodeLeaves {
        node: shared[1].node,
        children: tail,
    });
    // Refused on either path: a child out of range, a node origin that is not one.
    for (base, bad) in [&nodes, &shared]
        .into_iter()
        .flat_map(|b| [(b, (0, 1 << 12)), (b, (1, 0))])
    {
        let mut refused = base.clone();
        refused[1].node.x += bad.0;
        refused[1].children[0].0 += bad.1;
        let r = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
            Grid::<i8>::new().leaf_indices_or_insert(&refused)
        }));
        assert!(r.is_err(), "{bad:?} must be refused");
    }
    for (case, groups) in [nodes, shared].iter().enumerate() {
        let (mut grouped, mut single) = (Grid::<i8>::new(), Grid::<i8>::new());
        for g in [&mut grouped, &mut single] {
            for &o in &before {
                g.leaf_index_or_insert(o, None);
            }
        }
        let first_new = single.leaf_count() as u32;
        let want: Vec<(u32, (usize, bool))> = (groups.iter())
            .flat_map(|g| (g.children.iter()).map(|&(c, i)| (child_origin(g.node, c), i)))
            .map(|(o, i)| {
                let l = single.leaf_index_or_insert(o, None);
                (l, (i, l >= first_new))
            })
            .collect();
        let nodes_before = grouped.internals.len();
        let got = grouped.leaf_indices_or_insert(groups);
        assert!(grouped.internals.len() > nodes_before);
        assert_eq!(got, want, "case {case}");
        assert!(got.iter().any(|&(_, (_, new))| !new) && got.iter().any(|&(_, (_, new))| new));
        assert_eq!(grouped.leaf_count(), single.leaf_count());
        for &o in origins.iter().chain(&before) {
            assert_eq!(
                grouped.leaf_index_or_insert(o, None),
                single.leaf_index_or_insert(o, None)
            );
        }
        assert_eq!(
            grouped.leaf_count(),
            single.leaf_count(),
            "nothing new after"
        );
    }
}

#[test]
fn leaf_geometry() {
    let v = VoxelCoord::new(-1, 9, -9);
    assert_eq!(leaf_origin(v), VoxelCoord::new(-8, 8, -16));
    assert_eq!(voxel_at(leaf_origin(v), leaf_offset(v)), v);
}

#[test]
fn memory_grows_with_leaves_and_accessor_matches_get() {
    let mut g = Grid::<i8>::new();
    let m0 = g.memory_bytes();
    let mut rng = 12345u64;
    let mut next = || {
        rng ^= rng << 13;
        rng ^= rng >> 7;
        rng ^= rng << 17;
        (rng % 2000) as i32 - 1000
    };
    let mut pts = Vec::new();
    for _ in 0..5000 {
        let p = VoxelCoord::new(next(), next(), next());
        g.set(p, 1);
        pts.push(p);
    }
    assert!(g.memory_bytes() >= g.leaf_count() * std::mem::size_of::<Leaf<i8>>());
    assert!(g.memory_bytes() > m0);
    let mut acc = g.accessor();
    for _ in 0..20000 {
        let p = VoxelCoord::new(next(), next(), next());
        assert_eq!(acc.get(p), g.get(p));
    }
    for p in pts {
        assert_eq!(acc.get(p), Some(1));
    }
}

/// Each leaf once; each block's leaves together and by in-block index; blocks of one
/// internal node by origin (z, y, x); the same as the parallel form.
#[test]
fn block_order_groups_blocks_and_sorts_within() {
    let mut g = Grid::<i8>::new();
    let mut rng = crate::test_rng::Rng(7);
    let mut want = std::collections::BTreeSet::new();
    for _ in 0..3000 {
        let v = VoxelCoord::new(rng.i(-300, 300), rng.i(-300, 300), rng.i(-140, 140));
        g.set(v, 1);
        want.insert(leaf_origin(v));
    }
    let order: Vec<VoxelCoord> = g.leaves_in_block_order().map(|(o, _)| o).collect();
    assert_eq!(order.len(), want.len());
    assert_eq!(
        order
            .iter()
            .copied()
            .collect::<std::collections::BTreeSet<_>>(),
        want
    );
    let key = |o: VoxelCoord| {
        let b = block_origin(o);
        (internal_key(o), (b.z, b.y, b.x), leaf_in_block(o))
    };
    let mut done = std::collections::HashSet::new();
    for w in order.windows(2) {
        let (a, b) = (key(w[0]), key(w[1]));
        if a.0 == b.0 {
            assert!(a < b, "{:?} before {:?}", w[0], w[1]);
        }
        if block_origin(w[0]) != block_origin(w[1]) {
            assert!(done.insert(block_origin(w[0])), "block {:?} split", w[0]);
        }
    }
    let par = g.leaf_indices_in_block_order();
    assert_eq!(par.iter().map(|&(o, _)| o).collect::<Vec<_>>(), order);
    for (o, i) in par {
        assert_eq!(g.leaf_index(o), Some(i));
    }
    let v = VoxelCoord::new(-65, 70, 200);
    assert_eq!(block_origin(v), VoxelCoord::new(-128, 64, 192));
    assert_eq!(leaf_in_block(v), 7 + (1 << 6)); // (7, 0, 1)
    assert_eq!(
        leaf_of_block(block_origin(v), leaf_in_block(v)),
        leaf_origin(v)
    );
}

#[test]
fn a_removed_node_frees_its_slots_for_new_leaves_and_spares_the_others() {
    let mut g: Grid<i8> = Grid::new();
    let keep = VoxelCoord::new(130, 5, -3);
    g.set(keep, 9);
    let gone: Vec<VoxelCoord> = (0..40).map(|i| VoxelCoord::new(i * 3, i, 7)).collect();
    for &v in &gone {
        g.set(v, 4);
    }
    let (leaves, slots) = (g.leaf_count(), g.leaf_slots());
    let node = VoxelCoord::new(0, 0, 0);
    let removed = g.remove_node(node);
    assert!(removed > 5);
    assert_eq!(g.leaf_count(), leaves - removed);
    assert_eq!(g.remove_node(node), 0, "removed once");
    assert!(gone.iter().all(|&v| g.get(v).is_none()));
    assert_eq!(g.get(keep), Some(9));
    assert_eq!(g.node_count(), 1);
    // New leaves take the freed, zeroed slots before the pool grows, one by one and
    // in groups.
    g.set(VoxelCoord::new(0, 300, 0), 1);
    let groups = vec![NodeLeaves {
        node: VoxelCoord::new(0, 0, 256),
        children: (0..(removed as u16 - 1)).map(|c| (c, c)).collect(),
    }];
    let got = g.leaf_indices_or_insert(&groups);
    assert!(got.iter().all(|&(_, (_, new))| new));
    assert_eq!(g.leaf_slots(), slots, "no slot added");
    for &(l, _) in &got {
        let leaf = g.leaf(l);
        assert!(leaf.active.is_empty() && leaf.values.iter().all(|&v| v == 0));
    }
    assert_eq!(g.get(keep), Some(9));
    g.set(VoxelCoord::new(0, 0, 900), 2);
    assert_eq!(g.leaf_slots(), slots + 1, "then the pool grows");
}

#[test]
fn par_update_touches_each_listed_leaf_once() {
    let mut g = Grid::<i8>::new();
    let idx: Vec<u32> = (0..1000)
        .map(|i| g.leaf_index_or_insert(VoxelCoord::new(i * 8, 0, 0), None))
        .collect();
    let items: Vec<(u32, i8)> = idx
        .iter()
        .step_by(3)
        .map(|&i| (i, (i % 100) as i8))
        .collect();
    let n = g.leaf_pool_mut().par_update(
        &items,
        |_| (),
        |leaf, &v| {
            leaf.values[0] += v;
            leaf.active.set(0);
            1
        },
    );
    assert_eq!(n, items.len() as u64);
    for (k, &li) in idx.iter().enumerate() {
        let want = if k % 3 == 0 {
            Some((li % 100) as i8)
        } else {
            None
        };
        assert_eq!(g.leaf(li).get(0), want);
    }
}

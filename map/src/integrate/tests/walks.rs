//! The walks: the sides that split a frame between threads, the mark tables, and the dense
//! and sparse walks of every kernel agreeing.

use super::*;

/// The dense walk's sides cut across the sensor axis that sides a frame best, found
/// from a sample of its points, and only on more than one thread.
#[test]
fn sides_cut_across_the_axis_that_halves_the_frame() {
    let mut rng = Rng(5);
    let (pose, pts) = random_frame(&mut rng, 30000, 6.0);
    let origin = [1.0, 2.0, 3.0];
    // Keep the points with x and z in front (a sensor looking along x and z): only y
    // sides them.
    let front: Vec<_> = pts.iter().map(|p| [p[0].abs(), p[1], p[2].abs()]).collect();
    let frame = Frame {
        pose,
        points: &front,
    };
    assert!(Sides::new(&frame, origin, 1).axis.is_none());
    let axis = Sides::new(&frame, origin, 2).axis.unwrap();
    let y = pose.rotation * nalgebra::Vector3::y();
    assert!(
        (nalgebra::Vector3::from(axis) - y).norm() < 1e-12,
        "{axis:?}"
    );
    // Laid out by it: in front of the plane first, behind last, the gaps between.
    let s = Sides::new(&frame, origin, 2);
    let rays: Vec<_> = (0..RAY_CHUNK)
        .map(|i| match i % 5 {
            0 => Ray::new([0.0; 3], SKIPPED, false),
            _ => {
                let d = [0, 1, 2].map(|_| rng.f() - 0.5);
                Ray::new([0, 1, 2].map(|a| origin[a] + d[a]), 0, i % 3 == 0)
            }
        })
        .collect();
    let ahead = |r: &Ray| {
        (0..3)
            .map(|a| (r.end[a] - origin[a]) * axis[a])
            .sum::<f64>()
            >= 0.0
    };
    let mut out = vec![Ray::new([9.0; 3], 1, true); RAY_CHUNK];
    let (counts, order) = s.lay_out(&rays, &mut out);
    let [front, back] = counts.map(|c| c as usize);
    // The order says where each ray of the scan went.
    let mut places = vec![0u16; RAY_CHUNK];
    order.places(&mut places);
    for (j, r) in rays.iter().enumerate() {
        let made = r.key != SKIPPED;
        let bit = |m: &[u64]| m[j / 64] >> (j % 64) & 1 != 0;
        assert_eq!(
            (bit(&order.front), bit(&order.back)),
            (made && ahead(r), made && !ahead(r))
        );
        if made {
            assert_eq!(out[usize::from(places[j])].end, r.end);
        }
    }
    assert_eq!(front + back, RAY_CHUNK - RAY_CHUNK.div_ceil(5));
    assert!(out[..front].iter().all(|r| r.key != SKIPPED && ahead(r)));
    assert!(out[front..RAY_CHUNK - back]
        .iter()
        .all(|r| r.key == SKIPPED));
    assert!(out[RAY_CHUNK - back..]
        .iter()
        .all(|r| r.key != SKIPPED && !ahead(r)));
    let key = |r: &Ray| (r.end.map(f64::to_bits), r.hit);
    let mut laid: Vec<_> = out.iter().filter(|r| r.key != SKIPPED).map(key).collect();
    let mut made: Vec<_> = rays.iter().filter(|r| r.key != SKIPPED).map(key).collect();
    laid.sort_unstable();
    made.sort_unstable();
    assert_eq!(laid, made);
}

#[test]
fn tables_are_held_one_cache_each_and_merge_their_marks() {
    let mut marks = FrameMarks::default();
    let lo = VoxelCoord::new(-300, 0, 0);
    marks.reset(lo, VoxelCoord::new(300, 15, 15), 2);
    // Leaves (voxel coordinates >> 3) at both ends of the box and one in between.
    let shared = VoxelCoord::new(-1, 1, 0);
    let (only_a, only_b) = (VoxelCoord::new(-37, 0, 0), VoxelCoord::new(37, 1, 1));
    let mut a = marks.cache();
    let mut b = marks.cache();
    assert_ne!(a.table, b.table);
    let a_table = a.table;
    a.or_free(shared, &[1, 0, 0, 0, 0, 0, 0, 1 << 63]);
    a.or_free(only_a, &[0, 2, 0, 0, 0, 0, 0, 0]);
    b.or_free(shared, &[4, 0, 0, 0, 0, 0, 0, 0]);
    b.set_hit(shared.shl(3) + VoxelCoord::new(7, 7, 7));
    b.or_free(only_b, &[0, 0, 8, 0, 0, 0, 0, 0]);
    drop(a);
    assert_eq!(
        marks.cache().table,
        a_table,
        "a dropped cache frees its table"
    );
    drop(b);
    let leaves: Vec<(VoxelCoord, u32)> = (marks.leaves_in_order().iter())
        .flat_map(|g| (g.children.iter()).map(|&(c, s)| (crate::grid::child_origin(g.node, c), s)))
        .collect();
    let origins: Vec<_> = leaves.iter().map(|&(o, _)| o).collect();
    assert_eq!(origins, [only_a.shl(3), shared.shl(3), only_b.shl(3)]);
    // Read as the update reads them, leaving the slots zero for `clear_used` below.
    let words = |s: u32| {
        let slot = marks.slot(s);
        let taken: [(u64, u64); 8] = std::array::from_fn(|w| slot.take(w));
        (taken.map(|t| t.0), taken.map(|t| t.1))
    };
    let (free, hit) = words(leaves[1].1);
    assert_eq!(free, [5, 0, 0, 0, 0, 0, 0, 1 << 63]);
    assert_eq!(hit, [0, 0, 0, 0, 0, 0, 0, 1 << 63]);
    assert_eq!(words(leaves[0].1).0, [0, 2, 0, 0, 0, 0, 0, 0]);
    assert_eq!(words(leaves[2].1).0, [0, 0, 8, 0, 0, 0, 0, 0]);
    // A table's reserved ids that a cache left unused go to the table's next caches: one
    // batch per table, however many tasks take it, so distinct new leaves get distinct
    // ids from it; a new frame starts without them.
    let reserved = marks.slots.used();
    assert_eq!(reserved, 2 * super::marks::SLOT_BATCH);
    let mut ids = Vec::new();
    for x in 0..5 {
        let mut c = marks.cache();
        ids.push(c.slot_for(VoxelCoord::new(x, 1, 1)) as *const _);
    }
    assert_eq!(marks.slots.used(), reserved);
    ids.sort();
    ids.dedup();
    assert_eq!(ids.len(), 5);
    // Listed, as a frame lists its leaves, so that the tables are empty again.
    let listed: usize = (marks.leaves_in_order().iter())
        .map(|g| g.children.len())
        .sum();
    assert_eq!(listed, 5);
    marks.clear_used();
    marks.reset(lo, VoxelCoord::new(300, 15, 15), 2);
    marks.cache().slot_for(only_a);
    assert_eq!(marks.slots.used(), super::marks::SLOT_BATCH);
}

#[test]
fn dense_and_sparse_walks_agree() {
    let mut rng = Rng(29);
    // Short rays and long, many rays in a small box (most marks repeat, see
    // `avx512::walk_dense`), and a box too big for the dense grid.
    let mut frames: Vec<_> = [
        (5, 2.0),
        (3000, 4.0),
        (20000, 9.0),
        (3000, 25.0),
        (40000, 0.5),
        (4000, 45.0),
    ]
    .into_iter()
    .map(|(n, radius)| random_frame(&mut rng, n, radius))
    .collect();
    // Rays that end in the sensor's voxel, or along an axis.
    let (pose, _) = random_frame(&mut rng, 0, 1.0);
    let inv = pose.inverse();
    let at = |w: [f64; 3]| {
        let p = inv * Point3::new(w[0], w[1], w[2]);
        [p.x as f32, p.y as f32, p.z as f32]
    };
    let t = pose.translation.vector;
    let mut pts = vec![at([t.x, t.y, t.z]), at([t.x + 0.01, t.y, t.z])];
    pts.extend((0..20).map(|i| at([t.x + 0.1 * f64::from(i), t.y, t.z])));
    frames.push((pose, pts));
    // Long rays in the first eighth only: lanes done early take over others' rays.
    let (pose, mut pts) = random_frame(&mut rng, 16000, 0.5);
    pts[..2000]
        .iter_mut()
        .for_each(|p| *p = p.map(|c| c * 12.0));
    frames.push((pose, pts));
    // Non-finite points leave gaps in the rays' chunks (see `Sides`): scattered, and
    // filling a whole chunk. Then scans with every ray on one side of every sensor
    // axis, so on one side of the plane: one half of the walk's tasks has all the rays.
    let (pose, mut pts) = random_frame(&mut rng, 6000, 3.0);
    pts.iter_mut().step_by(7).for_each(|p| p[1] = f32::NAN);
    pts[1500..2600]
        .iter_mut()
        .for_each(|p| p[2] = f32::INFINITY);
    frames.push((pose, pts));
    for sign in [1.0f32, -1.0] {
        let (pose, mut pts) = random_frame(&mut rng, 5000, 3.0);
        pts.iter_mut().for_each(|p| *p = p.map(|c| sign * c.abs()));
        frames.push((pose, pts));
    }
    // Exact diagonals in 2 and 3 axes from a voxel centre, on a grid whose
    // coordinates are exact in binary: every corner and edge crossing is a tie.
    let q = 0.125;
    let sensor = Isometry3::translation(q / 2.0, q / 2.0, q / 2.0);
    let mut diag = Vec::new();
    for k in 1..40 {
        let d = (f64::from(k) * q) as f32;
        for s in [
            [1., 1., 1.],
            [-1., 1., -1.],
            [1., -1., 0.],
            [0., -1., -1.],
            [-1., 0., 1.],
        ] {
            diag.push([s[0] * d, s[1] * d, s[2] * d]);
        }
        // Ends on voxel corners and edges, in directions that are not diagonals.
        let c = |i: i32| (f64::from(i) * q - q / 2.0) as f32;
        diag.push([c(k), c(k / 2), c(-k / 3)]);
        diag.push([c(-k), c(k / 3), c(0)]);
    }
    // Many rays to lattice points around a voxel centre: ties everywhere, and enough rays
    // for the dense walk to find a covered box and skip it on the later rays.
    let lattice: Vec<[f32; 3]> = (0..30_000)
        .map(|_| std::array::from_fn(|_| ((rng.f() - 0.5) * 60.0).round() as f32 * q as f32))
        .collect();
    let grids = [(0.1, frames), (q, vec![(sensor, diag), (sensor, lattice)])];
    let run = |kernel: Kernel, walk: Walk| {
        let mut out = Vec::new();
        for (resolution, frames) in &grids {
            let mut map = OccupancyMap::new(*resolution, SensorModel::default()).unwrap();
            let mut integ = integrator(2, 40.0, RayMode::Exact);
            integ.walk = walk;
            integ.kernels = kernel.table().unwrap();
            let mut reports = Vec::new();
            for (pose, pts) in frames {
                let frame = Frame {
                    pose: *pose,
                    points: pts,
                };
                let r = integ.integrate(&mut map, &frame).unwrap();
                reports.push((
                    r.rays,
                    r.cut_rays,
                    r.voxel_steps,
                    r.touched_leaves,
                    r.touched_voxels,
                    r.dense,
                    r.covered_steps,
                ));
            }
            out.push((snapshot(&map), map.grid().leaf_count(), reports));
        }
        out
    };
    let sparse = run(Kernel::Scalar, Walk::Sparse);
    assert!(sparse.iter().flat_map(|g| &g.2).all(|r| !r.5));
    type Report = (u64, u64, u64, u64, u64, bool, u64);
    let covered_of = |g: &[(_, _, Vec<Report>)]| -> Vec<u64> {
        g.iter().flat_map(|g| &g.2).map(|r| r.6).collect()
    };
    let scalar_covered = covered_of(&run(Kernel::Scalar, Walk::Dense));
    let walks = [
        Walk::Sparse,
        Walk::Dense,
        Walk::DenseTestFirst,
        Walk::DenseGrouped,
        Walk::Auto,
    ];
    for kernel in kernels("dense_and_sparse_walks_agree") {
        for walk in walks {
            let dense = run(kernel, walk);
            let took_dense: Vec<bool> = dense.iter().flat_map(|g| &g.2).map(|r| r.5).collect();
            let covered: Vec<u64> = dense.iter().flat_map(|g| &g.2).map(|r| r.6).collect();
            if walk == Walk::Sparse {
                assert!(!took_dense.contains(&true));
                assert!(covered.iter().all(|&c| c == 0));
            } else if walk != Walk::Auto {
                assert_eq!(
                    took_dense,
                    [
                        true, true, true, true, true, false, true, true, true, true, true, true,
                        true
                    ]
                );
                // The frames of many rays skip a covered box, the lattice's too, and every
                // kernel skips the same steps.
                assert!(covered[2] > 0 && covered[12] > 0, "{covered:?}");
                assert_eq!(covered, scalar_covered, "{kernel:?} {walk:?}");
            }
            for (d, s) in dense.iter().zip(&sparse) {
                let strip = |r: &Report| (r.0, r.1, r.2, r.3, r.4);
                assert_eq!(
                    d.2.iter().map(strip).collect::<Vec<_>>(),
                    s.2.iter().map(strip).collect::<Vec<_>>(),
                    "{kernel:?} {walk:?}"
                );
                assert_eq!(d.1, s.1, "{kernel:?} {walk:?}");
                assert!(d.0 == s.0, "{kernel:?} {walk:?}: maps differ");
            }
        }
    }
}

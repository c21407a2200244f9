//! The integrator's tests: against a reference update written the slow way, across walks,
//! kernels, thread counts and ray modes.

use super::marks::FrameMarks;
use super::ray::{CellKeys, RayMaker, Sides, RAY_CHUNK, SKIPPED};
#[cfg(target_arch = "x86_64")]
use super::update::{avx512::Avx512, observe_scalar};
use super::*;
use crate::coord::VoxelCoord;
use crate::kernel::Kernel;
#[cfg(target_arch = "x86_64")]
use crate::model::QuantizedModel;
use crate::model::{SensorModel, VoxelState};
use crate::raycast::for_each_voxel;
use crate::test_rng::Rng;
use hashbrown::HashMap;
use nalgebra::Isometry3;
use nalgebra::{Translation3, UnitQuaternion};

/// Integrate `pts` seen from the origin, exact mode, 2 threads.
fn at_origin(map: &mut OccupancyMap, max_range: f64, pts: &[[f32; 3]]) -> IntegrateReport {
    let frame = Frame {
        pose: Isometry3::identity(),
        points: pts,
    };
    integrator(2, max_range, RayMode::Exact)
        .integrate(map, &frame)
        .unwrap()
}

fn integrator(threads: usize, max_range: f64, mode: RayMode) -> Integrator {
    Integrator::new(IntegratorConfig {
        threads,
        max_range,
        mode,
        ..Default::default()
    })
    .unwrap()
}

/// Whether the CPU runs `kernel`; prints a notice when it does not, so that a skipped test
/// of a kernel is seen, not silently absent.
fn kernel_or_notice(kernel: Kernel, test: &str) -> bool {
    let yes = kernel.supported();
    if !yes {
        crate::kernel::skip_notice(format_args!(
            "{test}: the {} kernel is skipped, this CPU lacks its instructions",
            kernel.name()
        ));
    }
    yes
}

/// The kernels to test on this CPU (each other kernel skipped with a notice).
fn kernels(test: &str) -> Vec<Kernel> {
    Kernel::ALL
        .into_iter()
        .filter(|&k| kernel_or_notice(k, test))
        .collect()
}

fn snapshot(map: &OccupancyMap) -> Vec<(VoxelCoord, i8)> {
    map.assert_marks_in_step();
    let mut v: Vec<_> = map.grid().active_voxels().collect();
    v.sort();
    v
}

/// The update rule written the slow, obvious way: per ray a list of voxels, hit beats
/// free within a frame, then one update per voxel.
fn reference_integrate(map: &mut OccupancyMap, frame: &Frame<'_>, max_range: f64) {
    let tf = *map.transform();
    let o = tf.point_to_units(&Point3::from(frame.pose.translation.vector));
    let range = max_range / tf.resolution();
    let mut marks: HashMap<VoxelCoord, bool> = HashMap::new();
    for p in frame.points {
        if !p.iter().all(|c| c.is_finite()) {
            continue;
        }
        let w = frame.pose * Point3::new(p[0] as f64, p[1] as f64, p[2] as f64);
        let mut e = tf.point_to_units(&w);
        let d: Vec<f64> = (0..3).map(|a| e[a] - o[a]).collect();
        let len = d.iter().map(|c| c * c).sum::<f64>().sqrt();
        let hit = len <= range;
        if !hit {
            e = [0, 1, 2].map(|a| o[a] + d[a] * range / len);
        }
        let mut path = Vec::new();
        for_each_voxel(o, e, |v| path.push(v));
        let end = path.pop().unwrap();
        for v in path {
            marks.entry(v).or_insert(false);
        }
        if hit {
            marks.insert(end, true);
        }
    }
    let q = *map.quantized();
    for (v, hit) in marks {
        let old = map.value(v).unwrap_or(0);
        map.set_value(v, q.update(old, hit));
    }
}

fn random_frame(rng: &mut Rng, n: usize, radius: f64) -> (Isometry3<f64>, Vec<[f32; 3]>) {
    let pose = Isometry3::from_parts(
        Translation3::new(rng.f() * 4.0 - 2.0, rng.f() * 4.0 - 2.0, rng.f() - 0.5),
        UnitQuaternion::from_euler_angles(rng.f() * 6.0, rng.f() - 0.5, rng.f() * 6.0),
    );
    (pose, (0..n).map(|_| rng.ball(radius)).collect())
}

#[test]
fn matches_the_reference_update_over_several_frames() {
    let mut rng = Rng(3);
    let frames: Vec<_> = (0..4).map(|_| random_frame(&mut rng, 3000, 4.0)).collect();
    let mut want = OccupancyMap::new(0.1, SensorModel::default()).unwrap();
    for (pose, pts) in &frames {
        let frame = Frame {
            pose: *pose,
            points: pts,
        };
        reference_integrate(&mut want, &frame, 3.0);
    }
    for kernel in kernels("matches_the_reference_update_over_several_frames") {
        let mut map = OccupancyMap::new(0.1, SensorModel::default()).unwrap();
        let mut integ = integrator(2, 3.0, RayMode::Exact);
        integ.kernels = kernel.table().unwrap();
        for (pose, pts) in &frames {
            let frame = Frame {
                pose: *pose,
                points: pts,
            };
            let r = integ.integrate(&mut map, &frame).unwrap();
            assert!(
                r.cut_rays > 0 && r.cut_rays < r.rays,
                "both kinds of rays: {r:?}"
            );
        }
        assert_eq!(snapshot(&map), snapshot(&want), "{kernel:?}");
    }
}

#[test]
fn result_is_identical_for_any_thread_count() {
    let mut rng = Rng(11);
    // Non-finite points leave gaps among the rays, laid out by sides from 2 threads
    // and in scan order on 1 (see `Sides`); the ray modes keep the first ray of a
    // kind, which must not depend on that layout.
    let frames: Vec<_> = (0..3)
        .map(|_| {
            let (pose, mut pts) = random_frame(&mut rng, 20000, 12.0);
            pts.iter_mut().step_by(11).for_each(|p| p[0] = f32::NAN);
            (pose, pts)
        })
        .collect();
    let run = |kernel: Kernel, threads, mode| {
        let mut map = OccupancyMap::new(0.1, SensorModel::default()).unwrap();
        let mut integ = integrator(threads, 10.0, mode);
        integ.kernels = kernel.table().unwrap();
        let mut steps = 0;
        for (pose, pts) in &frames {
            steps += integ
                .integrate(
                    &mut map,
                    &Frame {
                        pose: *pose,
                        points: pts,
                    },
                )
                .unwrap()
                .voxel_steps;
        }
        (snapshot(&map), steps, map.grid().leaf_count())
    };
    for mode in [
        RayMode::Exact,
        RayMode::Subsample { factor: 2 },
        RayMode::Bundle { threshold: 2 },
        RayMode::UniqueEnd,
    ] {
        // One thread of the scalar kernel is the reference for every kernel and count.
        let one = run(Kernel::Scalar, 1, mode);
        assert!(one.0.len() > 100_000);
        for kernel in kernels("result_is_identical_for_any_thread_count") {
            for t in [1, 2, 3, 4] {
                if (kernel, t) != (Kernel::Scalar, 1) {
                    assert!(
                        run(kernel, t, mode) == one,
                        "{mode:?}: {kernel:?} on {t} threads differs from scalar on 1"
                    );
                }
            }
        }
    }
}

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

/// The dense walks (eight rays at a time or one, into per-thread bit grids) and the
/// sparse walk (one ray at a time into shared leaves) give the same map, steps and report,
/// on frames with fewer rays than lanes, rays ending in their start voxel, rays cut at
/// max range, negative coordinates, and a frame too big for the dense box.
/// The vectorised observation of a leaf word gives the values the scalar one does:
/// random words and marks, under the default model and models that clamp at the ends
/// of i8 (where the vector add saturates) and inside them.
#[cfg(target_arch = "x86_64")]
#[test]
fn observing_a_word_at_once_equals_bit_by_bit() {
    use super::update::{avx2::Avx2, Observe};
    fn check<O: Observe>() {
        let default = SensorModel::default().quantize().unwrap();
        let wide = QuantizedModel {
            hit: 127,
            miss: -128,
            min: -128,
            max: 127,
            ..default
        };
        let narrow = QuantizedModel {
            hit: 90,
            miss: -70,
            min: -50,
            max: 60,
            ..default
        };
        // Every value at or above the threshold, a first miss's too.
        let low = QuantizedModel {
            threshold: default.min,
            ..default
        };
        let mut rng = Rng(7);
        let word = |rng: &mut Rng| {
            (rng.f() * 2f64.powi(32)) as u64 | ((rng.f() * 2f64.powi(32)) as u64) << 32
        };
        for q in [default, wide, narrow, low] {
            for k in 0..2000 {
                let (free, hit) = (word(&mut rng), word(&mut rng) & word(&mut rng));
                // Some words with a half (or all) unobserved.
                let any = (free | hit) & [!0, !0 << 32, !0 >> 32, 0][k % 4];
                let hit = hit & any;
                let old: [i8; 64] = std::array::from_fn(|_| rng.i(-128, 127) as i8);
                let (mut a, mut b) = (old, old);
                let marks = O::observe::<false>(&mut a, any, hit, &q);
                assert_eq!(marks, observe_scalar::<false>(&mut b, any, hit, &q));
                assert_eq!(a, b);
                let (mut a, mut b) = ([0i8; 64], [0i8; 64]);
                let marks = O::observe::<true>(&mut a, any, hit, &q);
                assert_eq!(marks, observe_scalar::<true>(&mut b, any, hit, &q));
                assert_eq!(a, b);
            }
        }
    }
    let test = "observing_a_word_at_once_equals_bit_by_bit";
    if kernel_or_notice(Kernel::Avx2, test) {
        check::<Avx2>();
    }
    if kernel_or_notice(Kernel::Avx512, test) {
        check::<Avx512>();
    }
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

/// Sensor inside a closed box room: every wall voxel hit is occupied, the interior the
/// rays crossed is free, and nothing outside the walls is known.
#[test]
fn closed_box_room() {
    let (hx, hy, hz) = (2.0f64, 1.5f64, 1.2f64); // half extents, metres; walls at +-h
    let sensor = [0.33f64, -0.21, 0.1];
    let mut pts = Vec::new();
    let n = 200_000;
    for i in 0..n {
        // Fibonacci sphere directions.
        let z = 1.0 - 2.0 * (i as f64 + 0.5) / n as f64;
        let r = (1.0 - z * z).sqrt();
        let phi = i as f64 * 2.399963229728653;
        let d = [r * phi.cos(), r * phi.sin(), z];
        let t = (0..3)
            .map(|a| {
                let h = [hx, hy, hz][a];
                if d[a] > 0.0 {
                    (h - 0.01 - sensor[a]) / d[a]
                } else if d[a] < 0.0 {
                    (-h + 0.01 - sensor[a]) / d[a]
                } else {
                    f64::INFINITY
                }
            })
            .fold(f64::INFINITY, f64::min);
        pts.push([0, 1, 2].map(|a| (d[a] * t) as f32));
    }
    let pose = Isometry3::translation(sensor[0], sensor[1], sensor[2]);
    let mut map = OccupancyMap::new(0.05, SensorModel::default()).unwrap();
    let r = integrator(2, 10.0, RayMode::Exact)
        .integrate(&mut map, &Frame { pose, points: &pts })
        .unwrap();
    assert_eq!(r.cut_rays, 0);
    let tf = *map.transform();
    let state = |x: f64, y: f64, z: f64| map.state_at(&WorldPointT::new(x, y, z));
    // The wall voxel of every point is occupied.
    for p in pts.iter().step_by(97) {
        let w = pose * Point3::new(p[0] as f64, p[1] as f64, p[2] as f64);
        assert_eq!(map.state_at(&w), VoxelState::Occupied, "{w:?}");
    }
    // The interior, at least two voxels from the walls, is free wherever rays crossed it;
    // with 200k rays from one point that is every voxel (checked on a lattice).
    let res = tf.resolution();
    let mut checked = 0;
    let steps = |h: f64| (-((h - 2.0 * res) / 0.1) as i32)..=(((h - 2.0 * res) / 0.1) as i32);
    for ix in steps(hx) {
        for iy in steps(hy) {
            for iz in steps(hz) {
                let (x, y, z) = (
                    ix as f64 * 0.1 + 0.013,
                    iy as f64 * 0.1 + 0.013,
                    iz as f64 * 0.1 + 0.013,
                );
                assert_eq!(state(x, y, z), VoxelState::Free, "interior ({x}, {y}, {z})");
                checked += 1;
            }
        }
    }
    assert!(checked > 5000);
    // Outside the walls: unknown, and no known voxel lies beyond them.
    assert_eq!(state(hx + 0.3, 0.0, 0.0), VoxelState::Unknown);
    assert_eq!(state(0.0, -hy - 0.3, 0.0), VoxelState::Unknown);
    assert_eq!(state(0.0, 0.0, hz + 0.5), VoxelState::Unknown);
    for (v, _) in map.grid().active_voxels() {
        let c = tf.voxel_center(v);
        assert!(
            c.x.abs() < hx + res && c.y.abs() < hy + res && c.z.abs() < hz + res,
            "known outside: {c:?}"
        );
    }
    let counts = map.counts();
    assert!(
        counts.occupied > 1000 && counts.free > 100_000,
        "{counts:?}"
    );
}

type WorldPointT = crate::coord::WorldPoint;

#[test]
fn max_range_rays_mark_free_only() {
    let mut map = OccupancyMap::new(0.1, SensorModel::default()).unwrap();
    let pts = [[5.0f32, 0.05, 0.05], [1.0, 0.05, 0.05]];
    let r = at_origin(&mut map, 2.0, &pts[..1]);
    assert_eq!((r.rays, r.cut_rays), (1, 1));
    assert_eq!(map.counts().occupied, 0);
    // Cut at 2 m along the ray: x = 1.9998, voxel 19 is the cut end.
    assert_eq!(map.state(VoxelCoord::new(18, 0, 0)), VoxelState::Free);
    assert_eq!(
        map.state(VoxelCoord::new(19, 0, 0)),
        VoxelState::Unknown,
        "the cut end itself is not marked"
    );
    at_origin(&mut map, 2.0, &pts[1..]);
    assert_eq!(map.state(VoxelCoord::new(10, 0, 0)), VoxelState::Occupied);

    // Cut at x = 16.5: the end voxel opens leaf 2 but is not marked, so no leaf 2.
    let mut map = OccupancyMap::new(0.1, SensorModel::default()).unwrap();
    at_origin(&mut map, 1.65, &pts[..1]);
    assert_eq!(map.state(VoxelCoord::new(15, 0, 0)), VoxelState::Free);
    let leaves: Vec<_> = map
        .grid()
        .leaves()
        .map(|(o, l)| (o.x, l.active.count()))
        .collect();
    assert_eq!(leaves.len(), 2, "{leaves:?}");
    assert!(leaves.iter().all(|&(x, n)| x < 16 && n == 8), "{leaves:?}");
}

/// Leaves mark their voxels at or above the threshold, also exactly at it (here one
/// hit's value), on every walk, in new leaves and in leaves seen before.
#[test]
fn leaves_mark_voxels_at_the_threshold() {
    let model = SensorModel {
        occupancy_threshold: SensorModel::default().p_hit,
        ..Default::default()
    };
    let kernels = kernels("leaves_mark_voxels_at_the_threshold");
    let runs = kernels
        .iter()
        .flat_map(|&k| [(k, Walk::Sparse), (k, Walk::Dense)]);
    for (kernel, walk) in runs {
        let mut map = OccupancyMap::new(0.1, model).unwrap();
        let q = *map.quantized();
        assert_eq!(q.threshold, q.hit);
        let mut integ = integrator(2, 5.0, RayMode::Exact);
        integ.walk = walk;
        integ.kernels = kernel.table().unwrap();
        let mut rng = Rng(5);
        for _ in 0..3 {
            let (pose, pts) = random_frame(&mut rng, 2000, 4.0);
            integ
                .integrate(&mut map, &Frame { pose, points: &pts })
                .unwrap();
            map.assert_marks_in_step();
        }
        let at = map
            .grid()
            .active_voxels()
            .filter(|&(_, v)| v == q.threshold);
        assert!(
            at.count() > 100,
            "{kernel:?} {walk:?}: few voxels at the threshold"
        );
    }
}

#[test]
fn hit_beats_free_within_a_frame_and_degenerate_rays() {
    let mut map = OccupancyMap::new(0.1, SensorModel::default()).unwrap();
    // The second point's ray passes through the first point's voxel.
    let pts = [
        [0.55f32, 0.05, 0.05],
        [1.55, 0.05, 0.05],
        [0.0, 0.0, 0.0],
        [0.01, 0.02, 0.03],
    ];
    at_origin(&mut map, 10.0, &pts);
    let q = *map.quantized();
    assert_eq!(map.value(VoxelCoord::new(5, 0, 0)), Some(q.hit));
    assert_eq!(map.value(VoxelCoord::new(15, 0, 0)), Some(q.hit));
    assert_eq!(map.value(VoxelCoord::new(10, 0, 0)), Some(q.miss));
    // Zero-length rays: the sensor's own voxel is a hit, once.
    assert_eq!(map.value(VoxelCoord::new(0, 0, 0)), Some(q.hit));
}

/// `make_all` (eight at a time with the AVX-512 kernel) makes exactly `make`'s rays: on
/// random points, non-finite ones, points on voxel faces and at max range, under
/// rotated poses.
#[test]
fn rays_made_in_bulk_equal_rays_made_one_by_one() {
    let mut rng = Rng(77);
    let tf = crate::coord::GridTransform::new(0.1).unwrap();
    for round in 0..20 {
        let (pose, mut pts) = random_frame(&mut rng, 1003, 8.0);
        let o = tf.point_to_units(&Point3::from(pose.translation.vector));
        let range = 5.0 / tf.resolution();
        // Some points on multiples of the resolution (faces under the identity pose),
        // exactly at max range, non-finite, or beyond max range.
        let pose = if round % 4 == 0 {
            Isometry3::identity()
        } else {
            pose
        };
        let bad = [f32::NAN, f32::INFINITY, f32::NEG_INFINITY];
        for (i, p) in pts.iter_mut().enumerate().step_by(3) {
            match i % 4 {
                0 => *p = p.map(|c| (c * 10.0).round() / 10.0),
                1 => *p = [5.0, 0.0, 0.0],
                2 => p[i % 3] = bad[i / 4 % 3],
                _ => *p = p.map(|c| c * 3.0),
            }
        }
        let frame = Frame { pose, points: &pts };
        for kernel in kernels("rays_made_in_bulk_equal_rays_made_one_by_one") {
            let maker = RayMaker::new(&frame, &tf, o, range, kernel.table().unwrap());
            let mut bulk = vec![Ray::new([0.0; 3], 0, false); pts.len()];
            maker.make_all(&mut bulk, &pts);
            for (p, b) in pts.iter().zip(&bulk) {
                let one = maker.make(p);
                assert_eq!(
                    (one.end.map(f64::to_bits), one.key, one.hit),
                    (b.end.map(f64::to_bits), b.key, b.hit),
                    "{kernel:?}, point {p:?}"
                );
            }
            // The ray modes' cell keys and the extent, noted as the rays are made:
            // the same bits as the scalar code's.
            for factor in [1, 2, 64] {
                let cells = CellKeys::new(o, factor);
                let mut keys = vec![0; bulk.len()];
                cells.keys(kernel.table().unwrap(), &bulk, &mut keys);
                for (r, &k) in bulk.iter().zip(&keys) {
                    assert_eq!(k, cells.key(r), "{kernel:?}, factor {factor}, {r:?}");
                }
                // And their notes in the box about the sensor and in the frame's box.
                let extent = super::ray::bounds(&bulk, o);
                let boxes = [
                    super::select::CellBox::around(o, range, &cells),
                    super::select::CellBox::new(&extent, &cells),
                ];
                let sides = [None, Some([0.6, -0.8, 0.0])].map(|axis| Sides { origin: o, axis });
                for (b, s) in boxes
                    .iter()
                    .flatten()
                    .flat_map(|b| sides.iter().map(move |s| (b, s)))
                {
                    let mut notes = vec![0; bulk.len()];
                    b.notes_of(&cells, s, kernel.table().unwrap(), &bulk, &mut notes);
                    for (r, &k) in bulk.iter().zip(&notes) {
                        let want = b.note_of(&cells, s, r);
                        assert_eq!(k, want, "{kernel:?}, factor {factor}, {r:?}");
                    }
                }
            }
            let sum = |s: super::ray::ExtentSum| {
                let bits = |v: [f64; 3]| v.map(f64::to_bits);
                (bits(s.lo), bits(s.hi), bits(s.length), s.cut, s.skipped)
            };
            for n in [0, 1, 2, 5, bulk.len()] {
                assert_eq!(
                    sum((kernel.table().unwrap().extent_of)(o, &bulk[..n])),
                    sum(super::ray::ExtentSum::of_scalar(o, &bulk[..n])),
                    "{kernel:?}, {n} rays"
                );
            }
            // Made and laid out by sides (in one pass on AVX2): the same rays in the same
            // places, the same orders and extent as the scalar kernel's, in whole chunks
            // and in shorter ones (a length not a multiple of four takes the two passes).
            // The last plane passes through a ray's end: that ray lies on it, in front.
            let scalar = RayMaker::new(&frame, &tf, o, range, Kernel::Scalar.table().unwrap());
            let on = bulk.iter().find(|r| r.key != SKIPPED).unwrap().end;
            let planes = [
                (o, None),
                (o, Some([0.6, -0.8, 0.0])),
                (o, Some([0.0, 0.0, -1.0])),
                (on, Some([0.6, -0.8, 0.0])),
            ];
            for (origin, axis) in planes {
                let sides = Sides { origin, axis };
                for len in [RAY_CHUNK, 500, 8, 7] {
                    let run = |m: &RayMaker| {
                        let mut out = vec![Ray::new([1.0; 3], 7, true); len];
                        let mut scratch = Vec::new();
                        let (counts, order, s) =
                            sides.make(m, &pts[..len], &mut out, &mut scratch, None);
                        let rays: Vec<_> = (out.iter())
                            .map(|r| (r.end.map(f64::to_bits), r.key, r.hit))
                            .collect();
                        (counts, order.front, order.back, order.cut, rays, sum(s))
                    };
                    assert!(
                        run(&maker) == run(&scalar),
                        "{kernel:?}, axis {axis:?}, {len} points"
                    );
                }
            }
        }
    }
}

#[test]
fn non_finite_points_are_skipped_and_counted() {
    let mut map = OccupancyMap::new(0.1, SensorModel::default()).unwrap();
    let pts = [
        [1.0f32, 0.0, 0.0],
        [f32::NAN, 0.0, 0.0],
        [0.0, f32::INFINITY, 0.0],
        [0.0, 1.0, 0.0],
    ];
    let r = at_origin(&mut map, 10.0, &pts);
    assert_eq!((r.points, r.skipped_nonfinite, r.rays), (4, 2, 2));
    assert_eq!(map.counts().occupied, 2);
}

#[test]
fn bad_frames_are_rejected_and_change_nothing() {
    let mut map = OccupancyMap::new(0.1, SensorModel::default()).unwrap();
    let mut integ = integrator(2, 10.0, RayMode::Exact);
    integ
        .integrate(
            &mut map,
            &Frame {
                pose: Isometry3::identity(),
                points: &[[1.0, 1.0, 1.0]],
            },
        )
        .unwrap();
    let before = snapshot(&map);
    let far = Isometry3::translation(1e9, 0.0, 0.0);
    assert!(matches!(
        integ.integrate(
            &mut map,
            &Frame {
                pose: far,
                points: &[[1.0, 0.0, 0.0]]
            }
        ),
        Err(IntegrateError::OriginOutOfRange { .. })
    ));
    let nan = Isometry3::translation(f64::NAN, 0.0, 0.0);
    assert_eq!(
        integ.integrate(
            &mut map,
            &Frame {
                pose: nan,
                points: &[[1.0, 0.0, 0.0]]
            }
        ),
        Err(IntegrateError::NonFinitePose)
    );
    assert_eq!(snapshot(&map), before);
    assert!(Integrator::new(IntegratorConfig {
        threads: 0,
        ..Default::default()
    })
    .is_err());
    assert!(Integrator::new(IntegratorConfig {
        max_range: f64::NAN,
        ..Default::default()
    })
    .is_err());
    let long = IntegratorConfig {
        max_range: 2000.0,
        threads: 1,
        ..Default::default()
    };
    assert_eq!(
        Integrator::new(long).unwrap().integrate(
            &mut map,
            &Frame {
                pose: Isometry3::identity(),
                points: &[]
            }
        ),
        Err(IntegrateError::RangeTooLong {
            max_range: 2000.0,
            resolution: 0.1
        })
    );
    assert_eq!(snapshot(&map), before);
}

/// A bundle no group exceeds casts every ray: the same rays, cut rays and map as exact,
/// on either thread count (the cut rays counted from the masks the making pass notes).
#[test]
fn a_bundle_that_merges_nothing_casts_what_exact_casts() {
    let mut rng = Rng(6);
    // Points out to 4 m against a 2.5 m range: many rays are cut.
    let pts: Vec<_> = (0..30_000).map(|_| rng.ball(4.0)).collect();
    let frame = Frame {
        pose: Isometry3::identity(),
        points: &pts,
    };
    for threads in [1, 2] {
        let run = |mode| {
            let mut map = OccupancyMap::new(0.1, SensorModel::default()).unwrap();
            let r = integrator(threads, 2.5, mode)
                .integrate(&mut map, &frame)
                .unwrap();
            (r.rays, r.cut_rays, snapshot(&map))
        };
        let exact = run(RayMode::Exact);
        assert!(exact.1 > 1000, "{}", exact.1);
        let all = run(RayMode::Bundle {
            threshold: 1_000_000,
        });
        assert!(all == exact, "{threads} threads");
    }
}

/// Frames with no rays to choose from (no points, or only non-finite ones) integrate in every
/// mode and on any thread count, casting nothing.
#[test]
fn trade_off_modes_take_frames_without_rays() {
    let nan = [f32::NAN; 3];
    for points in [vec![], vec![nan; 3], vec![nan; 5000]] {
        for mode in [
            RayMode::UniqueEnd,
            RayMode::Subsample { factor: 2 },
            RayMode::Bundle { threshold: 2 },
        ] {
            for threads in [1, 2] {
                let mut map = OccupancyMap::new(0.1, SensorModel::default()).unwrap();
                let frame = Frame {
                    pose: Isometry3::identity(),
                    points: &points,
                };
                let r = integrator(threads, 10.0, mode)
                    .integrate(&mut map, &frame)
                    .unwrap();
                assert_eq!((r.rays, r.skipped_nonfinite), (0, points.len() as u64));
            }
        }
    }
}

#[test]
fn trade_off_modes_cast_fewer_rays_and_stay_close() {
    let mut rng = Rng(5);
    // Dense: 50k points in a 1 m ball (~4200 voxels) at 0.1 m: many share end voxels.
    let pts: Vec<_> = (0..50_000).map(|_| rng.ball(1.0)).collect();
    let frame = Frame {
        pose: Isometry3::identity(),
        points: &pts,
    };
    let run = |mode| {
        let mut map = OccupancyMap::new(0.1, SensorModel::default()).unwrap();
        let r = integrator(2, 10.0, mode)
            .integrate(&mut map, &frame)
            .unwrap();
        (r, map.counts(), snapshot(&map))
    };
    let (exact, ce, se) = run(RayMode::Exact);
    for mode in [
        RayMode::UniqueEnd,
        RayMode::Subsample { factor: 1 },
        RayMode::Bundle { threshold: 2 },
    ] {
        let (r, c, _) = run(mode);
        assert!(
            r.rays < exact.rays / 2,
            "{mode:?}: {} of {} rays",
            r.rays,
            exact.rays
        );
        // Same end voxels: the occupied set is nearly unchanged.
        let d = (c.occupied as f64 - ce.occupied as f64).abs() / ce.occupied as f64;
        assert!(
            d < 0.05,
            "{mode:?}: occupied {} vs {}",
            c.occupied,
            ce.occupied
        );
    }
    // Unique-end keeps exactly one ray per end voxel: the occupied set is the same.
    assert_eq!(run(RayMode::UniqueEnd).1.occupied, ce.occupied);
    // A bundle threshold above every group size changes nothing.
    assert_eq!(
        run(RayMode::Bundle {
            threshold: 1_000_000
        })
        .2,
        se
    );
    // A very fine subsample grid (1.6 mm) keeps nearly every ray.
    assert!(run(RayMode::Subsample { factor: 64 }).0.rays * 1000 > exact.rays * 999);
}

/// Subsample and unique-end cast exactly the rays a hash set in scan order keeps, on each
/// of their three paths (rays chosen as they are made in the box about the sensor, chosen
/// afterwards in the frame's box, or in hash partitions), with every kernel and thread
/// count, and with buffers reused by frames of other sizes and modes: the same ends and
/// hits, the cut ones counted, all within the extent.
#[test]
fn modes_keep_what_the_scan_order_hash_keeps_on_every_path() {
    use super::prepare::prepare_rays;
    use super::ray::{ray_count, Ray};
    use super::select::{cell_factor, choose_hashed, Buffers, CellBox};
    let mut rng = Rng(21);
    let tf = crate::coord::GridTransform::new(0.1).unwrap();
    let mut frames: Vec<_> = [20_000, 5_000, 30_000]
        .map(|n| random_frame(&mut rng, n, 8.0))
        .into();
    for (_, pts) in &mut frames {
        for (i, p) in pts.iter_mut().enumerate() {
            // Repeats: points on a lattice of 0.5 m; some not finite.
            *p = p.map(|c| (c * 2.0).round() / 2.0);
            if i % 101 == 0 {
                p[i % 3] = f32::NAN;
            }
        }
    }
    // (range in metres, mode, which path).
    let cases = [
        (5.0, RayMode::UniqueEnd, "around"),
        (5.0, RayMode::Subsample { factor: 2 }, "around"),
        (30.0, RayMode::UniqueEnd, "extent"),
        (5.0, RayMode::Subsample { factor: 4 }, "hashed"),
    ];
    let mut select = Buffers::default();
    let (mut rays, mut counts) = (Vec::new(), Vec::new());
    for kernel in kernels("modes_keep_what_the_scan_order_hash_keeps_on_every_path") {
        for threads in [1, 2, 3] {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            for (&(range_m, mode, path), (pose, pts)) in cases.iter().zip(frames.iter().cycle()) {
                let frame = Frame {
                    pose: *pose,
                    points: pts,
                };
                let origin = tf.point_to_units(&Point3::from(pose.translation.vector));
                let range = range_m / tf.resolution();
                let maker =
                    RayMaker::new(&frame, &tf, origin, range, Kernel::Scalar.table().unwrap());
                let mut want: Vec<Ray> = (pts.iter().map(|p| maker.make(p)))
                    .filter(|r| r.key != SKIPPED)
                    .collect();
                let made = want.clone();
                choose_hashed(&mut want, origin, mode);
                assert!(want.len() * 10 < made.len() * 9, "{mode:?}: few dropped");
                let cells = CellKeys::new(origin, cell_factor(mode));
                let around = CellBox::around(origin, range, &cells).is_some();
                let extent = super::ray::bounds(&made, origin);
                let boxed = CellBox::new(&extent, &cells).is_some();
                let took = match (around, boxed) {
                    (true, _) => "around",
                    (false, true) => "extent",
                    (false, false) => "hashed",
                };
                assert_eq!(took, path, "{range_m} m, {mode:?}");
                let (skipped, extent, _) = pool.install(|| {
                    let sides = Sides::new(&frame, origin, threads);
                    prepare_rays(
                        &mut rays,
                        &mut counts,
                        sides,
                        &frame,
                        &tf,
                        origin,
                        range,
                        mode,
                        kernel.table().unwrap(),
                        &mut select,
                    )
                });
                let cast: Vec<Ray> = (rays.chunks(RAY_CHUNK).zip(&counts))
                    .flat_map(|(c, &[front, back])| {
                        let (f, b) = (front as usize, back as usize);
                        c[..f].iter().chain(&c[c.len() - b..]).copied()
                    })
                    .collect();
                assert_eq!(cast.len() as u64, ray_count(&counts));
                let ends = |v: &[Ray]| {
                    let mut e: Vec<_> =
                        v.iter().map(|r| (r.end.map(f64::to_bits), r.hit)).collect();
                    e.sort_unstable();
                    e
                };
                let at = format!("{path}: {mode:?}, {kernel:?} on {threads} threads");
                assert!(ends(&cast) == ends(&want), "{at}");
                assert_eq!(skipped as usize, pts.len() - made.len(), "{at}");
                let cut = want.iter().filter(|r| !r.hit).count() as u64;
                assert_eq!(extent.cut_rays, cut, "{at}");
                let inside = |r: &Ray| {
                    let v = r.end.map(|c| c.floor() as i32);
                    (0..3)
                        .all(|a| extent.lo.to_array()[a] <= v[a] && v[a] <= extent.hi.to_array()[a])
                };
                assert!(cast.iter().all(inside), "{at}");
            }
        }
    }
}

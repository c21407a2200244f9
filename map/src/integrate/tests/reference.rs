//! The update against a reference written the slow way: several frames, any thread count,
//! every kernel's observation, max-range rays, the threshold, hit beating free.

use super::*;

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
    use crate::integrate::update::{avx2::Avx2, Observe};
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

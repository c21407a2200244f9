//! The ray modes through the integrator: fewer rays, close maps, and the same rays on every
//! path as the one-pass reference.

use super::*;

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
fn ray_modes_take_frames_without_rays() {
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
fn ray_modes_cast_fewer_rays_and_stay_close() {
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

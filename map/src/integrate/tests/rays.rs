//! Rays made from points: in bulk as one by one, non-finite points skipped, bad frames
//! refused.

use super::*;

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

//! The AVX2 walks' tests: lane set-up, steps and marks against the one-ray walks.

use super::*;
use crate::raycast::{self, Dda};
use crate::test_rng::Rng;

/// One axis of one ray as `raycast::axis` sets it up, in lane form.
fn scalar(o: f64, e: f64, stride: i64) -> [i64; 5] {
    let (_, dir, t0, d, last, n) = raycast::axis(o, e);
    if n == 0 {
        return [NEVER, 0, 0, 0, 0];
    }
    [
        t0.min(T_CAP) as i64,
        d.min(T_CAP) as i64,
        last.min(T_CAP) as i64,
        i64::from(dir) * stride,
        i64::from(n),
    ]
}

/// The four-lane skip of the covered box (`Queue::skip_covered`) makes, ray by ray, the
/// crossings `Covered::skip` makes: the same next crossings, steps left and first voxel,
/// rays from a voxel centre to lattice points (ties) among them.
#[test]
fn four_lane_skip_equals_the_scalar_one() {
    if !is_x86_feature_detected!("avx2") {
        crate::kernel::skip_notice(format_args!(
            "this CPU has no AVX2; the AVX2 skip is not tested here"
        ));
        return;
    }
    let mut rng = Rng(5);
    let dbox = DenseBox::new(VoxelCoord::new(-64, -64, -64), VoxelCoord::new(63, 63, 63))
        .expect("a small box");
    let strides = dbox.strides();
    let mut checked = 0;
    for round in 0..400 {
        let origin: [f64; 3] = if round % 2 == 0 {
            std::array::from_fn(|_| (rng.f() - 0.5) * 8.0)
        } else {
            std::array::from_fn(|_| (rng.f() * 8.0).floor() - 3.5)
        };
        let s = crate::coord::units_to_voxel(origin).unwrap();
        let mut r = || VoxelCoord::from_array(std::array::from_fn(|_| (rng.f() * 20.0) as i32));
        let lo = s - r();
        let hi = s + r();
        let c = Covered::new(s, lo, hi);
        let rays: Vec<Ray> = (0..37)
            .map(|i| {
                let e: [f64; 3] = if i % 3 == 0 {
                    std::array::from_fn(|a| origin[a] + ((rng.f() - 0.5) * 80.0).round())
                } else {
                    std::array::from_fn(|a| origin[a] + (rng.f() - 0.5) * 100.0)
                };
                Ray::new(e, 0, true)
            })
            .collect();
        // SAFETY: AVX2 was detected above.
        let axes = std::array::from_fn(|a| unsafe {
            Axis::new(origin[a], strides[a], dbox.lo.to_array()[a], dbox.n[a])
        });
        let start = dbox.index(s);
        let from = Start {
            axes: &axes,
            origin,
            start,
            covered: Some(&c),
        };
        let mut feed = Feed::all(&rays);
        // SAFETY: AVX2 was detected above.
        let mut q = unsafe { Queue::new() };
        let mut at = 0;
        // SAFETY: AVX2 was detected above.
        while unsafe { q.fill(&mut feed, &from) } {
            for j in 0..q.len {
                let dda = Dda::new(origin, rays[at + j].end);
                let (t, d, last, dir) = dda.axes();
                let made = c.skip(t, d, last, dir);
                let want = dda.after(made);
                let (t, ..) = want.axes();
                let lane = |v: &[__m256i; 3], a: usize| to_array(v[a])[j % 4];
                let got_t = [0, 1, 2].map(|a| lane(&q.t[j / 4], a));
                let want_t = t.map(|t| {
                    if t == u64::MAX {
                        NEVER
                    } else {
                        t.min(T_CAP) as i64
                    }
                });
                assert_eq!(got_t, want_t, "ray {} from {origin:?}", at + j);
                assert_eq!(q.n[j], i64::from(want.steps()));
                assert_eq!(q.p0[j] as u64, dbox.index(want.voxel()));
                checked += usize::from(made != [0; 3]);
            }
            at += q.len;
        }
        assert_eq!(at, rays.len());
    }
    assert!(checked > 5000, "{checked}");
}

#[test]
fn four_lane_setup_equals_the_scalar_one_bit_for_bit() {
    if !is_x86_feature_detected!("avx2") {
        crate::kernel::skip_notice(format_args!(
            "this CPU has no AVX2; the AVX2 set-up is not tested here"
        ));
        return;
    }
    let mut rng = Rng(7);
    let mut cases: Vec<(f64, f64)> = Vec::new();
    // On faces, just off them, tiny and long crossings, both directions.
    for o in [
        0.0,
        0.5,
        1.0,
        1.0 - 1e-16,
        3.999_999_999,
        -2.0,
        -0.25,
        100.125,
    ] {
        for de in [0.0, 1e-300, 1e-16, 0.5, 1.0, 1.5, 2.0, 63.0, 64.75, 8191.5] {
            cases.push((o, o + de));
            cases.push((o, o - de));
        }
    }
    for _ in 0..200_000 {
        let o = (rng.f() - 0.5) * 200.0;
        let len = if rng.f() < 0.5 {
            rng.f() * 4.0
        } else {
            rng.f() * 2000.0
        };
        cases.push((o, o + (rng.f() - 0.5) * len));
    }
    let stride = 1 << 12;
    for (o, group) in cases
        .chunks(4)
        .flat_map(|g| [g[0].0, 1.0, -3.5].map(|o| (o, g)))
    {
        // Every ray of a group from one origin, as in a frame.
        let ends: Vec<f64> = group.iter().map(|&(go, e)| o + (e - go)).collect();
        let mut e4 = [o; 4];
        e4[..ends.len()].copy_from_slice(&ends);
        // SAFETY: AVX2 was detected above.
        let got = unsafe {
            let axis = Axis::new(o, stride, -100_000, 200_000);
            axis.setup(_mm256_set_pd(e4[3], e4[2], e4[1], e4[0]))
        };
        for (l, &e) in e4.iter().enumerate() {
            let want = scalar(o, e, stride);
            let lane: [i64; 5] = std::array::from_fn(|k| to_array(got[k])[l]);
            assert_eq!(lane, want, "origin {o:e}, end {e:e}");
            assert_eq!(
                to_array(got[5])[l],
                -1,
                "origin {o:e}, end {e:e} is in the box"
            );
        }
    }
}

#[test]
fn a_walk_marks_within_its_box_and_stops_at_an_end_outside_it() {
    if !is_x86_feature_detected!("avx2") {
        crate::kernel::skip_notice(format_args!(
            "this CPU has no AVX2; the AVX2 walk is not tested here"
        ));
        return;
    }
    use crate::coord::VoxelCoord;
    // Box voxels 0..64 x 0..8 x 0..8, origin in voxel (2, 2, 2).
    let dbox = DenseBox::new(VoxelCoord::new(0, 0, 0), VoxelCoord::new(63, 7, 7)).unwrap();
    let origin = [2.5, 2.5, 2.5];
    // Both dense walks: in groups and lane by lane.
    for grouped in [false, true] {
        let walk = |ends: &[[f64; 3]]| {
            let rays: Vec<Ray> = ends.iter().map(|&e| Ray::new(e, 0, true)).collect();
            let mut ranges: [Range<usize>; 8] = Default::default();
            ranges[0] = 0..rays.len();
            let mut bits = DenseBits::default();
            bits.begin(1, dbox.words());
            // SAFETY: AVX2 was detected above.
            let (steps, _) =
                unsafe { walk_dense(&mut bits, &dbox, origin, &rays, ranges, None, grouped) };
            (steps, bits)
        };
        // Inside: a ray along x to voxel (60, 2, 2) marks voxels 2..60 free and 60 hit.
        let (steps, bits) = walk(&[[60.5, 2.5, 2.5]]);
        assert_eq!(steps, 59);
        let row = bits.free[(dbox.index(VoxelCoord::new(0, 2, 2)) / 64) as usize];
        assert_eq!(row, ((1u64 << 60) - 1) & !0b11);
        let word = (dbox.index(VoxelCoord::new(0, 2, 2)) / 64) as usize;
        assert_eq!(bits.hit[word], 1 << 60);
        // Nothing else in the box (idle lanes mark the sinks, past it).
        let marked: u32 = bits.free[..dbox.words()]
            .iter()
            .map(|w| w.count_ones())
            .sum();
        assert_eq!(marked, 58);
        // An end outside the box stops the walk before it reads or writes outside it.
        for end in [[64.5, 2.5, 2.5], [2.5, 8.5, 2.5], [2.5, 2.5, -0.5]] {
            let outcome = std::panic::catch_unwind(|| walk(&[[3.5, 3.5, 3.5], end]));
            assert!(outcome.is_err(), "end {end:?} outside the box");
        }
    }
}

#[test]
fn ends_outside_the_box_are_found() {
    if !is_x86_feature_detected!("avx2") {
        crate::kernel::skip_notice(format_args!(
            "this CPU has no AVX2; the AVX2 set-up is not tested here"
        ));
        return;
    }
    // Box voxels -4..12 along the axis.
    // SAFETY: AVX2 was detected above.
    let inside = unsafe {
        let axis = Axis::new(0.5, 1, -4, 16);
        to_array(axis.setup(_mm256_set_pd(12.0, 11.999, -4.0, -4.001))[5])
    };
    assert_eq!(inside, [0, -1, -1, 0]);
}

//! The ray modes' tests: every path of each mode against the one-pass reference, across
//! kernels, sides and thread counts.

use super::*;
use crate::integrate::prepare::compact;
use crate::integrate::ray::{bounds, SKIPPED};
use crate::test_rng::Rng;

/// What a ray mode casts of `rays` (made in scan order): keys noted, laid out by
/// sides across `axis` as the prepare phase does it, chosen and compacted, with each
/// supported kernel (all giving the same rays). Returned per chunk, the rays in front
/// in scan order, then those behind in scan order; across no axis, the rays kept in
/// scan order.
fn thinned(
    rays: &[Ray],
    origin: [f64; 3],
    mode: RayMode,
    extent: &Extent,
    bufs: &mut Buffers,
    axis: Option<[f64; 3]>,
) -> Vec<Ray> {
    let mut got: Option<Vec<Ray>> = None;
    for kernel in crate::kernel::Kernel::available() {
        let kernels = kernel.table().expect("an available kernel");
        let cells = CellKeys::new(origin, cell_factor(mode));
        let sides = Sides { origin, axis };
        let mut laid = rays.to_vec();
        let mut counts = Vec::new();
        let (keys, orders) = bufs.notes(rays.len());
        cells.keys(kernels, rays, keys);
        for ((made, out), order) in (rays.chunks(RAY_CHUNK))
            .zip(laid.chunks_mut(RAY_CHUNK))
            .zip(orders.iter_mut())
        {
            let (chunk_counts, o) = sides.lay_out(made, out);
            counts.push(chunk_counts);
            let mut cut = [0u64; RAY_CHUNK / 64];
            for (j, r) in made.iter().enumerate() {
                cut[j / 64] |= u64::from(r.key != SKIPPED && !r.hit) << (j % 64);
            }
            *order = ChunkOrder { cut, ..o };
        }
        let (kept, orders) = choose(&mut laid, origin, mode, extent, bufs);
        let cut = compact(&mut laid, &mut counts, orders, &kept);
        let cast: Vec<Ray> = (laid.chunks(RAY_CHUNK).zip(&counts))
            .flat_map(|(c, &[front, back])| {
                let (f, b) = (front as usize, back as usize);
                c[..f].iter().chain(c[c.len() - b..].iter().rev()).copied()
            })
            .collect();
        // The rays cast lie in the box of all rays; their cut ones are counted.
        let want = bounds(&cast, origin);
        assert!(extent
            .lo
            .to_array()
            .iter()
            .zip(want.lo.to_array())
            .all(|(a, b)| *a <= b));
        assert!(extent
            .hi
            .to_array()
            .iter()
            .zip(want.hi.to_array())
            .all(|(a, b)| *a >= b));
        assert_eq!(cut, want.cut_rays, "{mode:?} {kernel:?}");
        let fields = |v: &[Ray]| v.iter().map(|r| (r.end, r.hit, r.key)).collect::<Vec<_>>();
        if let Some(g) = &got {
            assert!(fields(g) == fields(&cast), "{mode:?}: {kernel:?} differs");
        }
        got = Some(cast);
    }
    got.expect("the scalar kernel runs anywhere")
}

/// Rays as a sorted list of their fields' bits: the rays cast, whatever their order.
fn as_set(v: &[Ray]) -> Vec<([u64; 3], bool, u32)> {
    let mut s: Vec<_> = v
        .iter()
        .map(|r| (r.end.map(f64::to_bits), r.hit, r.key))
        .collect();
    s.sort_unstable();
    s
}

/// A cell's bit in 64-bit arithmetic, from the box's definition: the reference for
/// [`CellBox::bit`]'s 32 bits.
fn bit_in_64_bits(b: &CellBox, key: u64) -> u64 {
    let c = [0, 1, 2].map(|a| {
        let k = (key >> (21 * a) & CellKeys::FIELD) as i64 - i64::from(b.lo[a]);
        k.clamp(0, i64::from(b.dims[a]) - 1) as u64
    });
    let d = b.dims.map(u64::from);
    let cell = (c[2] * d[1] + c[1]) * d[0] + c[0];
    cell << b.hit_bit | (key >> 63 & u64::from(b.hit_bit))
}

/// [`CellBox::bits_of`] (vectorised, 32 bits) agrees with the 64-bit reference key by
/// key: ends inside the box, outside it (clamped to its faces), hit or not, and
/// skipped points.
#[test]
fn bits_of_agrees_with_64_bit_reference() {
    let mut rng = Rng(7);
    let origin = [0.25, 0.5, -0.75];
    for factor in [1, 2] {
        let cells = CellKeys::new(origin, factor);
        let rays: Vec<Ray> = (0..20_000)
            .map(|i| {
                let end = [0, 1, 2].map(|a| origin[a] + rng.f() * 12.0 - 6.0);
                Ray::new(end, 0, i % 3 != 0)
            })
            .collect();
        // A box of the first few ends only: most keys lie outside it. And one of a
        // cell a bit (no ray cut at max range).
        let small = bounds(&rays[..50], origin);
        let mut one_bit = bounds(&rays, origin);
        one_bit.cut_rays = 0;
        let mut hit_bits = Vec::new();
        for extent in [bounds(&rays, origin), small, one_bit] {
            let b = CellBox::new(&extent, &cells).unwrap();
            hit_bits.push(b.hit_bit);
            let mut keys: Vec<u64> = rays.iter().map(|r| cells.key(r)).collect();
            keys.insert(7, NO_CELL);
            let mut bits = vec![0; keys.len()];
            b.bits_of(&keys, &mut bits);
            for (&k, &got) in keys.iter().zip(&bits) {
                let want = if k == NO_CELL {
                    u32::MAX
                } else {
                    bit_in_64_bits(&b, k) as u32
                };
                assert!(want < b.bits() as u32 || k == NO_CELL);
                assert_eq!(got, want, "key {k:#x}");
            }
        }
        assert_eq!(hit_bits, [1, 1, 0]);
    }
}

/// The bit-set path keeps exactly the rays, with the ends, that the
/// hash set in scan order keeps, on any number of threads; rays on the box's faces,
/// repeated cells and skipped points included; the hash partitions too.
#[test]
fn dense_firsts_keep_what_the_scan_order_hash_keeps() {
    let mut rng = Rng(11);
    let origin = [3.5, -2.25, 0.5];
    let mut rays: Vec<Ray> = (0..60_000)
        .map(|i| {
            if i % 97 == 0 {
                return Ray::new([0.0; 3], SKIPPED, false);
            }
            // Ends on a coarse lattice (many repeats, some exactly on cell faces).
            let end = [0, 1, 2].map(|a| origin[a] + (rng.f() * 20.0 - 10.0).round() / 2.0);
            Ray::new(end, 0, i % 3 != 0)
        })
        .collect();
    rays.push(Ray::new(origin, 0, true));
    let made: Vec<Ray> = rays.iter().copied().filter(|r| r.key != SKIPPED).collect();
    let extent = bounds(&rays, origin);
    let mut bufs = Buffers::default();
    for mode in [
        RayMode::UniqueEnd,
        RayMode::Subsample { factor: 1 },
        RayMode::Subsample { factor: 4 },
    ] {
        let mut want = made.clone();
        choose_hashed(&mut want, origin, mode);
        assert!(
            want.len() < made.len() / 2 && want.len() > 1000,
            "{mode:?}: {}",
            want.len()
        );
        for threads in [1, 2, 3, 5] {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            // Buffers left by the modes and thread counts before.
            let got = pool.install(|| thinned(&rays, origin, mode, &extent, &mut bufs, None));
            // The same rays (a chunk's may change order as dropped ones leave it).
            assert_eq!(as_set(&got), as_set(&want), "{mode:?} on {threads} threads");
        }
    }
    // A box too large for bit sets takes the partitioned hash sets: the same rays.
    let cells = |f| CellKeys::new(origin, f);
    assert!(CellBox::new(&extent, &cells(64)).is_none());
    assert!(CellBox::new(&extent, &cells(1)).is_some());
    for (mode, factor) in [
        (RayMode::Subsample { factor: 4 }, 4),
        (RayMode::UniqueEnd, 1),
    ] {
        let mut want = made.clone();
        choose_hashed(&mut want, origin, mode);
        for threads in [1, 3] {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            let keys: Vec<u64> = rays.iter().map(|r| cells(factor).key(r)).collect();
            let keep: Vec<AtomicBool> = keys.iter().map(|_| AtomicBool::new(false)).collect();
            pool.install(|| first_per_cell_hashed(&keys, &keep));
            let got: Vec<Ray> = (rays.iter().zip(&keep))
                .filter(|(r, k)| r.key != SKIPPED && k.load(Ordering::Relaxed))
                .map(|(r, _)| {
                    if mode == RayMode::UniqueEnd {
                        to_centre(r)
                    } else {
                        *r
                    }
                })
                .collect();
            let ends = |v: &[Ray]| v.iter().map(|r| (r.end, r.hit)).collect::<Vec<_>>();
            assert!(
                ends(&got) == ends(&want),
                "{mode:?} hashed on {threads} threads"
            );
        }
    }
    let mut want = made.clone();
    choose_hashed(&mut want, origin, RayMode::Subsample { factor: 64 });
    let mode = RayMode::Subsample { factor: 64 };
    let got = thinned(&rays, origin, mode, &extent, &mut Buffers::default(), None);
    assert_eq!(got.len(), want.len());
}

/// A small frame in a large box has its sets cleared by the bits it marked (when the
/// next frame chooses): the frames after it choose as with fresh buffers.
#[test]
fn sets_cleared_by_their_bits_leave_nothing_behind() {
    let mut rng = Rng(14);
    let origin = [0.5; 3];
    let frame = |rng: &mut Rng| -> Vec<Ray> {
        (0..2000)
            .map(|i| {
                // Repeats within the frame: ends on a lattice of 4 voxels.
                let end = [0, 1, 2].map(|_| (rng.f() * 25.0).floor() * 4.0 - 50.0);
                Ray::new(end, 0, i % 2 == 0)
            })
            .collect()
    };
    let mut bufs = Buffers::default();
    for _ in 0..4 {
        let rays = frame(&mut rng);
        let extent = bounds(&rays, origin);
        let cells = CellKeys::new(origin, 1);
        // A box of about 100^3 voxels, each of two bits, against 1000 rays a run.
        let b = CellBox::new(&extent, &cells).unwrap();
        assert!(b.bits() / 64 > 1000 * 8, "{}", b.bits());
        for threads in [1, 2] {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            let mode = RayMode::UniqueEnd;
            let got = pool.install(|| thinned(&rays, origin, mode, &extent, &mut bufs, None));
            let mut fresh = Buffers::default();
            let want = pool.install(|| thinned(&rays, origin, mode, &extent, &mut fresh, None));
            assert!(got.len() < rays.len() && got.len() > 1000, "{}", got.len());
            assert_eq!(as_set(&got), as_set(&want));
        }
    }
}

/// Laid out by sides, a mode casts the same rays, with the same extent (checked in
/// `thinned`), as in scan order: dropped rays leave the layout, kept ones keep their
/// side and order.
#[test]
fn the_layout_keeps_what_the_mode_keeps() {
    let mut rng = Rng(13);
    let origin = [0.5, 1.5, -0.5];
    let rays: Vec<Ray> = (0..20_000)
        .map(|i| {
            let end = [0, 1, 2].map(|a| origin[a] + (rng.f() * 16.0 - 8.0).round() / 2.0);
            Ray::new(end, 0, i % 4 != 0)
        })
        .collect();
    let extent = bounds(&rays, origin);
    let sort = |mut v: Vec<([f64; 3], bool)>| {
        v.sort_by(|a, b| a.partial_cmp(b).unwrap());
        v
    };
    let axis = [0.6, 0.8, 0.0];
    for mode in [
        RayMode::UniqueEnd,
        RayMode::Bundle { threshold: 2 },
        RayMode::Subsample { factor: 2 },
    ] {
        let mut bufs = Buffers::default();
        let want = thinned(&rays, origin, mode, &extent, &mut bufs, None);
        assert!(want.len() < rays.len() / 2, "{mode:?}");
        let got = thinned(&rays, origin, mode, &extent, &mut bufs, Some(axis));
        let pairs = |v: &[Ray]| sort(v.iter().map(|r| (r.end, r.hit)).collect());
        assert!(pairs(&got) == pairs(&want), "{mode:?}");
    }
}

/// Bundles: the same groups and means as the sort-based reference (which sums a group
/// in another order: equal to rounding), and exactly the same rays on any thread count,
/// by the counting sort and by the hash partitions.
#[test]
fn bundles_match_the_sorted_reference_on_any_thread_count() {
    let mut rng = Rng(12);
    let origin = [0.25, 0.5, -0.75];
    let rays: Vec<Ray> = (0..50_000)
        .map(|i| {
            let end = [0, 1, 2].map(|a| origin[a] + rng.f() * 12.0 - 6.0);
            Ray::new(end, 0, i % 5 != 0)
        })
        .collect();
    let extent = bounds(&rays, origin);
    let sorted = |v: &[Ray]| {
        let mut e: Vec<_> = v
            .iter()
            .map(|r| (r.end.map(f64::floor), r.hit, r.end))
            .collect();
        e.sort_by(|a, b| a.partial_cmp(b).unwrap());
        e
    };
    for threshold in [1, 3, 1_000_000] {
        let mode = RayMode::Bundle { threshold };
        let mut want = rays.clone();
        choose_hashed(&mut want, origin, mode);
        let pool = |n| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(n)
                .build()
                .unwrap()
        };
        let mut bufs = Buffers::default();
        let one = pool(1).install(|| thinned(&rays, origin, mode, &extent, &mut bufs, None));
        let (w, g) = (sorted(&want), sorted(&one));
        assert_eq!(w.len(), g.len(), "threshold {threshold}");
        for (a, b) in w.iter().zip(&g) {
            assert_eq!((a.0, a.1), (b.0, b.1));
            assert!(
                (0..3).all(|k| (a.2[k] - b.2[k]).abs() < 1e-9),
                "{a:?} {b:?}"
            );
        }
        if threshold == 1_000_000 {
            // No group is bundled: every ray, in scan order.
            let ends = |v: &[Ray]| v.iter().map(|r| r.end).collect::<Vec<_>>();
            assert!(ends(&one) == ends(&rays));
        } else {
            assert!(
                one.len() < rays.len() * 9 / 10,
                "{} of {}",
                one.len(),
                rays.len()
            );
        }
        let fields = |v: &[Ray]| v.iter().map(|r| (r.end, r.hit, r.key)).collect::<Vec<_>>();
        for n in [2, 3, 5] {
            let got = pool(n).install(|| thinned(&rays, origin, mode, &extent, &mut bufs, None));
            assert!(
                fields(&got) == fields(&one),
                "threshold {threshold} on {n} threads"
            );
        }
        // The partitioned hash tables, which boxes too large for the counting sort
        // take, bundle exactly the same rays.
        let cells = CellKeys::new(origin, 1);
        assert!(CellBox::new(&extent, &cells).is_some());
        let keys: Vec<u64> = rays.iter().map(|r| cells.key(r)).collect();
        let places: Vec<u16> = (0..rays.len()).map(|i| (i % RAY_CHUNK) as u16).collect();
        for n in [1, 3] {
            let mut got = rays.clone();
            let keep: Vec<AtomicBool> = keys.iter().map(|_| AtomicBool::new(false)).collect();
            let layout = Layout { places: &places };
            let means = pool(n).install(|| bundle_hashed(&got, &layout, threshold, &keys, &keep));
            set_means(&mut got, origin, means);
            let got: Vec<Ray> = (got.iter().zip(&keep))
                .filter(|(_, k)| k.load(Ordering::Relaxed))
                .map(|(r, _)| *r)
                .collect();
            assert_eq!(
                as_set(&got),
                as_set(&one),
                "hashed, threshold {threshold} on {n} threads"
            );
        }
    }
}

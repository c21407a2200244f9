//! The covered box of a dense walk: a box around the sensor's voxel in which the rays
//! walked first have already marked every voxel (free or hit), so that the rays walked
//! after them need not walk inside it.
//!
//! Every ray starts in the sensor's voxel, so the voxels near the sensor are crossed by
//! nearly every ray of a frame: once a part of the frame's rays has been walked, a box
//! around the sensor is usually marked through and through. A later ray's voxels inside
//! it would only be marked again, so its walk starts where it first leaves the box, in
//! the exact state the whole walk would reach there ([`Covered::skip`],
//! [`crate::raycast::Dda::after`]); a ray ending inside keeps only its hit. The marks,
//! and so the map, are those of the whole walk: the update reads a voxel's free and hit
//! marks as one observation, the hit winning.

use super::dense::{DenseBits, DenseBox};
use crate::coord::VoxelCoord;
use crate::integrate::ray::{Ray, SKIPPED};
use crate::raycast::{crossings_by, kth_crossing, Dda};

/// Rays of a frame sampled to tell whether its covered box is worth skipping.
const SAMPLE: usize = 256;

/// A box of voxels around the sensor's, all marked in the union of the dense grids.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct Covered {
    pub(crate) lo: VoxelCoord,
    pub(crate) hi: VoxelCoord,
    /// Per axis, the crossings from the sensor's voxel out of the box: down, up.
    pub(crate) leave: [[u64; 2]; 3],
    /// The steps a ray saves in the box, on average over [`Covered::find`]'s sample.
    pub(crate) saves: u64,
}

impl Covered {
    /// The box grown from the sensor's voxel face by face, one layer at a time, for as
    /// long as the layer is marked through in `grids` (free or hit) and inside the frame's
    /// voxel bounds `lo..=hi`; `None` if it would not save a sample of `rays` enough steps
    /// to pay for finding where each ray leaves it. Only the voxels a ray can reach need
    /// marks: those nearer than `range` (voxel units, the rays' longest) to the sensor at
    /// `origin`, so the box of a flat scan can grow to its range's corners.
    pub(crate) fn find(
        grids: &[&DenseBits],
        dbox: &DenseBox,
        origin: [f64; 3],
        range: f64,
        (lo, hi): (VoxelCoord, VoxelCoord),
        rays: &[Ray],
    ) -> Option<Self> {
        // A ray's crossings lie within its length of the sensor, at most `range` (and the
        // rounding of a cut ray's end): a voxel it enters is nearer than that.
        let reach = range * (1.0 + 1e-9) + 1e-6;
        // Distance from the sensor to voxel `v`'s span on axis `a`.
        let gap = |v: i32, a: usize| {
            (f64::from(v) - origin[a])
                .max(origin[a] - f64::from(v) - 1.0)
                .max(0.0)
        };
        let start = crate::coord::units_to_voxel(origin).expect("origin checked");
        let (s, lo_a, hi_a) = (start.to_array(), lo.to_array(), hi.to_array());
        // Per row (y, z) of the bounds, the run of x around the sensor's voxel whose voxels
        // are all marked or out of reach, found when first asked for: so a layer across x
        // is one compare a row, and each row's bits are read once.
        let (ny, nz) = ((hi.y - lo.y + 1) as usize, (hi.z - lo.z + 1) as usize);
        let row_run = |y: i32, z: i32| -> (i32, i32) {
            let r2 = reach * reach - gap(y, 1).powi(2) - gap(z, 2).powi(2);
            if r2 <= 0.0 {
                return (lo.x, hi.x);
            }
            // Voxel x is within reach where x - 1 - r < origin < x + r.
            let r = r2.sqrt();
            let from = lo.x.max((origin[0] - r - 1.0).floor() as i32 + 1);
            let to = hi.x.min((origin[0] + r).ceil() as i32 - 1);
            let at = |x: i32| dbox.index(VoxelCoord::new(x, y, z));
            let up = (s[0] <= to)
                .then(|| unmarked(grids, at(s[0].max(from)), at(to), true))
                .flatten();
            let down = (from <= s[0])
                .then(|| unmarked(grids, at(from), at(s[0].min(to)), false))
                .flatten();
            let x = |i: u64| dbox.voxel(i).x;
            (
                down.map_or(lo.x, |i| x(i) + 1),
                up.map_or(hi.x, |i| x(i) - 1),
            )
        };
        // Each run as its ends' offsets from `lo.x`, plus one, in the two sides of a word: 0
        // (never a run, whose first end is at least `lo.x`) for a row not read yet. Zeroed
        // memory: a big box's rows cost nothing until read.
        let mut runs = vec![0u64; ny * nz];
        let mut run = |y: i32, z: i32| -> (i32, i32) {
            let k = (y - lo.y) as usize + ny * (z - lo.z) as usize;
            if runs[k] == 0 {
                let (l, h) = row_run(y, z);
                runs[k] = ((l - lo.x + 1) as u64) << 32 | u64::from((h - lo.x + 1) as u32);
            }
            let end = |v: u64| (v as u32) as i32 - 1 + lo.x;
            (end(runs[k] >> 32), end(runs[k]))
        };
        let (mut b_lo, mut b_hi) = (s, s);
        // The bounds on x of the box's rows' runs; the box holds only rows whose run holds
        // its span on x.
        let (mut runs_lo, mut runs_hi) = run(s[1], s[2]);
        if runs_lo > s[0] || runs_hi < s[0] {
            return None;
        }
        // Faces still growing: axis and side (0 down, 1 up). A face that meets an unmarked
        // voxel stops for good: its later layers, only wider, hold that voxel too.
        let mut growing = [[true; 2]; 3];
        while growing.iter().flatten().any(|&g| g) {
            for (a, sides) in growing.iter_mut().enumerate() {
                for (side, g) in sides.iter_mut().enumerate().filter(|(_, g)| **g) {
                    let c = if side == 0 { b_lo[a] - 1 } else { b_hi[a] + 1 };
                    let layer = c >= lo_a[a]
                        && c <= hi_a[a]
                        && match a {
                            0 => c >= runs_lo && c <= runs_hi,
                            _ => {
                                // The layer's rows: along z for a y layer, along y for a z one.
                                let o = 3 - a;
                                let (mut l, mut h) = (runs_lo, runs_hi);
                                let holds = (b_lo[o]..=b_hi[o]).all(|k| {
                                    let row = if a == 1 { run(c, k) } else { run(k, c) };
                                    (l, h) = (l.max(row.0), h.min(row.1));
                                    l <= b_lo[0] && h >= b_hi[0]
                                });
                                if holds {
                                    (runs_lo, runs_hi) = (l, h);
                                }
                                holds
                            }
                        };
                    match (layer, side) {
                        (false, _) => *g = false,
                        (true, 0) => b_lo[a] = c,
                        (true, _) => b_hi[a] = c,
                    }
                }
            }
        }
        let covered = Covered::new(
            start,
            VoxelCoord::from_array(b_lo),
            VoxelCoord::from_array(b_hi),
        );
        let every = (rays.len() / SAMPLE).max(1);
        let sample: Vec<_> = (rays.iter().step_by(every))
            .filter(|r| r.key != SKIPPED)
            .map(|r| Dda::new(origin, r.end).axes())
            .collect();
        let saved: u64 = (sample.iter())
            .map(|&(t, d, last, dir)| covered.skip(t, d, last, dir).iter().sum::<u64>())
            .sum();
        // Finding where a ray leaves the box costs about what a few steps do.
        let saves = saved / sample.len().max(1) as u64;
        (saved > 0 && saves >= 8).then_some(Covered { saves, ..covered })
    }

    /// The box `lo..=hi` for rays from the voxel `start`, which it holds.
    pub(crate) fn new(start: VoxelCoord, lo: VoxelCoord, hi: VoxelCoord) -> Self {
        let (s, l, h) = (start.to_array(), lo.to_array(), hi.to_array());
        debug_assert!((0..3).all(|a| l[a] <= s[a] && s[a] <= h[a]));
        Covered {
            lo,
            hi,
            leave: std::array::from_fn(|a| [(s[a] - l[a] + 1) as u64, (h[a] - s[a] + 1) as u64]),
            saves: 0,
        }
    }

    /// How many crossings of each axis a ray's walk from the sensor's voxel makes before
    /// it first leaves the box (all of them if it ends inside): per axis its first
    /// crossing `t0` (`u64::MAX`, or any value with `d` 0, for none), between crossings
    /// `d`, the last `last`, its direction `dir`. The crossings made are those before the
    /// one that leaves: every walk passes through that state, whatever its ties.
    #[inline]
    pub(crate) fn skip(
        &self,
        t0: [u64; 3],
        d: [u64; 3],
        last: [u64; 3],
        dir: [i32; 3],
    ) -> [u64; 3] {
        let leave = (0..3)
            .map(|a| match dir[a] {
                0 => u64::MAX,
                s => kth_crossing(t0[a], d[a], last[a], self.leave[a][usize::from(s > 0)]),
            })
            .min()
            .unwrap_or(u64::MAX);
        let by = match leave {
            0 => return [0; 3],
            u64::MAX => u64::MAX,
            t => t - 1,
        };
        std::array::from_fn(|a| crossings_by(t0[a], d[a], last[a], by))
    }
}

/// The first (`up`) or last bit of `from..=to` set in neither the free nor the hit marks
/// of any grid.
fn unmarked(grids: &[&DenseBits], from: u64, to: u64, up: bool) -> Option<u64> {
    let word = |w: usize| !grids.iter().fold(0, |m, g| m | g.free[w] | g.hit[w]);
    let (first, last) = ((from / 64) as usize, (to / 64) as usize);
    // Word `w`'s bits in the range.
    let part = |w: usize| {
        let lo = if w == first { !0 << (from % 64) } else { !0 };
        let hi = if w == last { !0 >> (63 - to % 64) } else { !0 };
        word(w) & lo & hi
    };
    let at = |w: usize, b: u32| Some(w as u64 * 64 + u64::from(b));
    if up {
        (first..=last).find_map(|w| match part(w) {
            0 => None,
            m => at(w, m.trailing_zeros()),
        })
    } else {
        (first..=last).rev().find_map(|w| match part(w) {
            0 => None,
            m => at(w, 63 - m.leading_zeros()),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::raycast::Dda;
    use crate::test_rng::Rng;

    /// The box grows to the frame's bounds where every voxel in reach is marked (those out
    /// of reach need none), and stops a face at the first layer with an unmarked voxel.
    #[test]
    fn the_box_grows_until_an_unmarked_voxel_in_reach() {
        let dbox = DenseBox::new(VoxelCoord::new(-16, -16, -16), VoxelCoord::new(15, 15, 15))
            .expect("a small box");
        let origin = [0.5, 0.25, 0.75];
        let range = 10.0;
        let mut bits = DenseBits::default();
        bits.begin(1, dbox.words());
        let near = |v: VoxelCoord| {
            let g = |c: i32, o: f64| (f64::from(c) - o).max(o - f64::from(c) - 1.0).max(0.0);
            let (x, y, z) = (g(v.x, origin[0]), g(v.y, origin[1]), g(v.z, origin[2]));
            (x * x + y * y + z * z).sqrt() < range + 0.5
        };
        let all: Vec<VoxelCoord> = (-16..16)
            .flat_map(|z| (-16..16).flat_map(move |y| (-16..16).map(move |x| (x, y, z))))
            .map(|(x, y, z)| VoxelCoord::new(x, y, z))
            .collect();
        for &v in all.iter().filter(|&&v| near(v)) {
            super::super::dense::set_bit(&mut bits.free, dbox.index(v));
        }
        let bounds = (VoxelCoord::new(-16, -16, -15), VoxelCoord::new(15, 14, 15));
        // Rays to points in reach: each would walk 5-20 voxels, all in the box.
        let rays: Vec<Ray> = (0..64)
            .map(|i| {
                let a = f64::from(i) * 0.7;
                Ray::new(
                    [origin[0] + 8.0 * a.cos(), origin[1] + 8.0 * a.sin(), 2.0],
                    0,
                    true,
                )
            })
            .collect();
        let find = |bits: &DenseBits| Covered::find(&[bits], &dbox, origin, range, bounds, &rays);
        let c = find(&bits).expect("worth it");
        assert_eq!((c.lo, c.hi), bounds);
        // A hole in reach, three voxels up x: that face stops just before it.
        let hole = dbox.index(VoxelCoord::new(3, 0, 0));
        bits.free[(hole / 64) as usize] &= !(1 << (hole % 64));
        let c = find(&bits).expect("worth it");
        assert_eq!((c.lo, c.hi), (bounds.0, VoxelCoord::new(2, 14, 15)));
        // The hole as a hit instead: marked again.
        super::super::dense::set_bit(&mut bits.hit, hole);
        assert_eq!(find(&bits).map(|c| c.hi), Some(bounds.1));
        // Rays that end near the sensor save too little to be worth a box.
        let short: Vec<Ray> = (rays.iter())
            .map(|r| Ray::new([origin[0] + 1.5, r.end[1].min(1.5), 1.2], 0, true))
            .collect();
        assert_eq!(
            Covered::find(&[&bits], &dbox, origin, range, bounds, &short),
            None
        );
    }

    /// The walk made by `skip` is the step-by-step walk's first steps, all inside the box,
    /// and it stops at the box's face: at most two steps more (ties at the leaving time,
    /// taken first by the lower axes) stay inside.
    #[test]
    fn skip_lands_where_the_step_by_step_walk_leaves_the_box() {
        let mut rng = Rng(11);
        let mut checked = 0;
        for i in 0..20_000 {
            // Every other ray from a voxel centre to a lattice point: crossings tie.
            let o: [f64; 3] = if i % 2 == 0 {
                std::array::from_fn(|_| (rng.f() - 0.5) * 20.0)
            } else {
                std::array::from_fn(|_| (rng.f() * 20.0).floor() - 9.5)
            };
            let e: [f64; 3] = if i % 2 == 0 {
                std::array::from_fn(|a| o[a] + (rng.f() - 0.5) * 60.0)
            } else {
                std::array::from_fn(|a| o[a] + 0.5 + ((rng.f() - 0.5) * 40.0).round())
            };
            let dda = Dda::new(o, e);
            let s = dda.voxel();
            let mut r = || VoxelCoord::from_array(std::array::from_fn(|_| (rng.f() * 12.0) as i32));
            let lo = s - r();
            let hi = s + r();
            let c = Covered::new(s, lo, hi);
            let (t, d, last, dir) = dda.axes();
            let made = c.skip(t, d, last, dir);
            let jumped = dda.after(made);
            let inside = |v: VoxelCoord| {
                let (v, l, h) = (v.to_array(), lo.to_array(), hi.to_array());
                (0..3).all(|a| l[a] <= v[a] && v[a] <= h[a])
            };
            let mut walk = dda.clone();
            for _ in 0..made.iter().sum::<u64>() {
                assert!(inside(walk.voxel()), "{o:?} -> {e:?}");
                walk.step();
            }
            assert!(inside(walk.voxel()));
            assert_eq!(walk, jumped, "{o:?} -> {e:?} in {lo:?}..{hi:?}");
            let mut more = 0;
            while walk.steps() > 0 {
                walk.step();
                if !inside(walk.voxel()) {
                    break;
                }
                more += 1;
            }
            assert!(more <= 2, "{o:?} -> {e:?}: {more} steps more inside");
            checked += usize::from(made != [0; 3]);
        }
        assert!(checked > 10_000);
    }
}

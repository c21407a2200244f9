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
use crate::raycast::{crossings_by, kth_crossing};

/// A box of voxels around the sensor's, all marked in the union of the dense grids.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(in crate::integrate) struct Covered {
    pub(in crate::integrate) lo: VoxelCoord,
    pub(in crate::integrate) hi: VoxelCoord,
    /// Per axis, the crossings from the sensor's voxel out of the box: down, up.
    pub(in crate::integrate) leave: [[u64; 2]; 3],
}

impl Covered {
    /// The box grown from the sensor's voxel `start` face by face, one layer at a time, for
    /// as long as the layer is marked through in `grids` (free or hit) and inside the
    /// frame's voxel bounds `lo..=hi`; `None` if it would not save enough steps to pay
    /// for finding where each ray leaves it.
    pub(in crate::integrate) fn find(
        grids: &[&DenseBits],
        dbox: &DenseBox,
        start: VoxelCoord,
        lo: VoxelCoord,
        hi: VoxelCoord,
    ) -> Option<Self> {
        let marked = |v: VoxelCoord, len: u64| all_marked(grids, dbox.index(v), len);
        let (start_a, lo_a, hi_a) = (start.to_array(), lo.to_array(), hi.to_array());
        if !marked(start, 1) {
            return None;
        }
        let (mut b_lo, mut b_hi) = (start_a, start_a);
        // Faces still growing: axis and side (0 down, 1 up). A face that meets an unmarked
        // voxel stops for good: its later layers, only wider, hold that voxel too.
        let mut growing = [[true; 2]; 3];
        while growing.iter().flatten().any(|&g| g) {
            for (a, sides) in growing.iter_mut().enumerate() {
                for (side, g) in sides.iter_mut().enumerate().filter(|(_, g)| **g) {
                    let c = if side == 0 { b_lo[a] - 1 } else { b_hi[a] + 1 };
                    let (mut l, mut h) = (b_lo, b_hi);
                    (l[a], h[a]) = (c, c);
                    let layer = c >= lo_a[a]
                        && c <= hi_a[a]
                        && (l[2]..=h[2]).all(|z| {
                            (l[1]..=h[1]).all(|y| {
                                let v = VoxelCoord::new(l[0], y, z);
                                marked(v, (h[0] - l[0] + 1) as u64)
                            })
                        });
                    match (layer, side) {
                        (false, _) => *g = false,
                        (true, 0) => b_lo[a] = c,
                        (true, _) => b_hi[a] = c,
                    }
                }
            }
        }
        // A ray saves about its length inside the box, and finding where it leaves costs
        // about what a dozen steps do.
        let reach: i32 = (0..3).map(|a| b_hi[a] - b_lo[a]).sum();
        if reach < 3 * 8 {
            return None;
        }
        Some(Covered::new(
            start,
            VoxelCoord::from_array(b_lo),
            VoxelCoord::from_array(b_hi),
        ))
    }

    /// The box `lo..=hi` for rays from the voxel `start`, which it holds.
    pub(in crate::integrate) fn new(start: VoxelCoord, lo: VoxelCoord, hi: VoxelCoord) -> Self {
        let (s, l, h) = (start.to_array(), lo.to_array(), hi.to_array());
        debug_assert!((0..3).all(|a| l[a] <= s[a] && s[a] <= h[a]));
        Covered {
            lo,
            hi,
            leave: std::array::from_fn(|a| [(s[a] - l[a] + 1) as u64, (h[a] - s[a] + 1) as u64]),
        }
    }

    /// How many crossings of each axis a ray's walk from the sensor's voxel makes before
    /// it first leaves the box (all of them if it ends inside): per axis its first
    /// crossing `t0` (`u64::MAX`, or any value with `d` 0, for none), between crossings
    /// `d`, the last `last`, its direction `dir`. The crossings made are those before the
    /// one that leaves: every walk passes through that state, whatever its ties.
    #[inline]
    pub(in crate::integrate) fn skip(
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

/// Whether bits `at..at + len` are set in the union of the grids' free and hit marks.
fn all_marked(grids: &[&DenseBits], at: u64, len: u64) -> bool {
    let (mut i, end) = (at, at + len);
    while i < end {
        let (w, b) = ((i / 64) as usize, i % 64);
        let n = (end - i).min(64 - b);
        let want = if n == 64 { !0 } else { ((1u64 << n) - 1) << b };
        let have = grids.iter().fold(0, |m, g| m | g.free[w] | g.hit[w]);
        if have & want != want {
            return false;
        }
        i += n;
    }
    true
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::raycast::Dda;
    use crate::test_rng::Rng;

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

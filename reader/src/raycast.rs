//! Exact 3D DDA (Amanatides & Woo) in continuous voxel units.
//!
//! A ray from `o` to `e` visits every voxel its segment passes through, each once, in order,
//! from `floor(o)` to `floor(e)`: exactly `|Δx| + |Δy| + |Δz|` steps, one axis at a time.
//! When the segment crosses an edge or corner exactly, the tie goes to the lowest axis
//! (x, then y, then z), so the walk is deterministic. Step counts are fixed up front, so
//! rounding can never carry the walk past the end voxel. [`LeafWalk`] follows the same walk
//! leaf by leaf (8x8x8 voxels) for walks that can pass whole leaves.
//!
//! Every DDA walk of voxmap is this one, stepped in its own way (the integration walks are
//! in `voxmap-map`'s `integrate::walk`):
//!
//! | walk | where | what for |
//! |---|---|---|
//! | [`Dda::step`], [`for_each_voxel`] | here | the reference; tests' slow paths |
//! | sparse, one ray at a time | `walk::sparse::walk_rays` | integration, frames with a large box |
//! | sparse, four rays per vector | `walk::avx2::walk_sparse` | the same, on AVX2 |
//! | sparse, eight rays per vector | `walk::avx512::walk_sparse` | the same, on AVX-512 |
//! | dense, one ray at a time | `walk::dense::walk_rays` | integration, frames with a small box |
//! | dense, four rays per vector | `walk::avx2::walk_dense` | the same, on AVX2 |
//! | dense, eight rays per vector | `walk::avx512::walk_dense` | the same, on AVX-512 |
//! | [`LeafWalk`] (whole leaves) and [`Dda::after_crossing`] | `snapshot::view` (`first_hit`) | line of sight on a snapshot |
//!
//! `voxmap-map`'s `integrate::tests::walks::dense_and_sparse_walks_agree` ties the
//! integration walks together (map and step counts); the tests here pin [`Dda`] against a
//! brute-force walk, and `snapshot::tests::queries::first_hit_agrees_on_long_and_lattice_segments`
//! the snapshot's.

use crate::coord::VoxelCoord;

/// Fixed-point scale of the ray parameter `t` in [0, 1]: t = 1 is `1 << T_BITS`.
/// Face crossings are kept as integers so a step is compare, select, add: a short
/// dependency chain in registers. With 60 fractional bits the accumulated rounding over
/// the longest walk (65536 voxels per axis, a snapshot's `first_hit`; integration rays are
/// at most 8192) stays below 1e-13 of the ray.
const T_BITS: u32 = 60;
#[doc(hidden)]
pub const T_ONE: f64 = (1u64 << T_BITS) as f64;

/// The state of one traversal. Call [`Dda::step`] exactly [`Dda::steps`] times.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Dda {
    pub x: i32,
    pub y: i32,
    pub z: i32,
    sx: i32,
    sy: i32,
    sz: i32,
    /// `t` of the next face crossing per axis (u64::MAX once the axis is done).
    tx: u64,
    ty: u64,
    tz: u64,
    dx: u64,
    dy: u64,
    dz: u64,
    /// `t` of the last crossing per axis.
    lx: u64,
    ly: u64,
    lz: u64,
    steps: u32,
}

/// Per-axis setup: (step, first crossing, delta, last crossing, crossings).
#[inline(always)]
#[doc(hidden)]
pub fn axis(o: f64, e: f64) -> (i32, i32, u64, u64, u64, u32) {
    let s = o.floor();
    let t = e.floor();
    let n = (t as i64 - s as i64).unsigned_abs() as u32;
    if n == 0 {
        return (s as i32, 0, u64::MAX, 0, u64::MAX, 0);
    }
    // floor(o) != floor(e) implies e != o on this axis: no division by zero.
    let inv = 1.0 / (e - o).abs();
    let face_dist = if t > s { s + 1.0 - o } else { o - s };
    let t0 = (face_dist * inv * T_ONE) as u64;
    let d = (inv * T_ONE) as u64;
    let last = t0.saturating_add(d.saturating_mul(u64::from(n - 1)));
    (s as i32, if t > s { 1 } else { -1 }, t0, d, last, n)
}

impl Dda {
    /// A walk from `o` to `e` (voxel units, finite, within the index space).
    #[inline(always)]
    pub fn new(o: [f64; 3], e: [f64; 3]) -> Self {
        let (x, sx, tx, dx, lx, nx) = axis(o[0], e[0]);
        let (y, sy, ty, dy, ly, ny) = axis(o[1], e[1]);
        let (z, sz, tz, dz, lz, nz) = axis(o[2], e[2]);
        Dda {
            x,
            y,
            z,
            sx,
            sy,
            sz,
            tx,
            ty,
            tz,
            dx,
            dy,
            dz,
            lx,
            ly,
            lz,
            steps: nx + ny + nz,
        }
    }

    /// Voxel steps left to the end voxel.
    #[inline]
    pub fn steps(&self) -> u32 {
        self.steps
    }

    /// Move to the next voxel, along the axis whose face comes first (ties: x, y, z).
    #[inline(always)]
    pub fn step(&mut self) {
        let cx = self.tx <= self.ty && self.tx <= self.tz;
        let cy = !cx && self.ty <= self.tz;
        let cz = !cx && !cy;
        // Next crossing per axis, computed off the critical path; an axis is done after its
        // last crossing.
        // Saturating: a done axis (u64::MAX) is not its last crossing, and its sum, though
        // never selected, must not overflow.
        let nx = if self.tx == self.lx {
            u64::MAX
        } else {
            self.tx.saturating_add(self.dx)
        };
        let ny = if self.ty == self.ly {
            u64::MAX
        } else {
            self.ty.saturating_add(self.dy)
        };
        let nz = if self.tz == self.lz {
            u64::MAX
        } else {
            self.tz.saturating_add(self.dz)
        };
        self.tx = if cx { nx } else { self.tx };
        self.ty = if cy { ny } else { self.ty };
        self.tz = if cz { nz } else { self.tz };
        self.x += self.sx & -(cx as i32);
        self.y += self.sy & -(cy as i32);
        self.z += self.sz & -(cz as i32);
        self.steps -= 1;
    }

    /// [`Dda::step`] without the check that an axis is done, for any step but the last two
    /// ([`Dda::steps`] > 2); call [`Dda::settle`] before those. Fewer live values, so the
    /// hot loop keeps them in registers.
    ///
    /// Why it is exact: an axis past its last crossing would next cross at t >= 1, and it
    /// can only be taken instead of a due crossing if rounding (under 2^18 of the 2^60
    /// units of t: at most one unit per crossing, 65536 crossings per axis) puts it below
    /// every crossing still due. All of those would then lie within that rounding of t = 1;
    /// crossings of one axis are at least 2^44 units apart (walks are at most 65536 voxels
    /// per axis), so at most one per other axis, two in all, can be there: it can only
    /// happen in the last two steps.
    //
    // Written out rather than shared with `step` through a `next`-crossing closure: that
    // version walked rays 20-25% slower (interleaved A/B, 500k 6 m workloads).
    #[inline(always)]
    pub fn step_far(&mut self) {
        let (cx, cy, cz) = self.step_far_crossing();
        self.x += self.sx & -(cx as i32);
        self.y += self.sy & -(cy as i32);
        self.z += self.sz & -(cz as i32);
    }

    /// The crossing half of [`Dda::step_far`] (same conditions): advances `t` and returns
    /// which axis is crossed, one-hot, leaving the voxel fields for the caller to move.
    /// For walkers that keep the voxel in their own form.
    #[inline(always)]
    pub fn step_far_crossing(&mut self) -> (bool, bool, bool) {
        debug_assert!(self.steps > 2);
        let cx = self.tx <= self.ty && self.tx <= self.tz;
        let cy = !cx && self.ty <= self.tz;
        let cz = !cx && !cy;
        // Saturating: after its last crossing an axis with a huge delta must stay last.
        self.tx = if cx {
            self.tx.saturating_add(self.dx)
        } else {
            self.tx
        };
        self.ty = if cy {
            self.ty.saturating_add(self.dy)
        } else {
            self.ty
        };
        self.tz = if cz {
            self.tz.saturating_add(self.dz)
        } else {
            self.tz
        };
        self.steps -= 1;
        (cx, cy, cz)
    }

    /// Per-axis step directions (-1, 0 or 1).
    pub fn direction(&self) -> [i32; 3] {
        [self.sx, self.sy, self.sz]
    }

    /// After [`Dda::step_far`]s: mark the axes past their last crossing as done, as
    /// [`Dda::step`] would have.
    #[inline(always)]
    pub fn settle(&mut self) {
        for (t, l) in [
            (&mut self.tx, self.lx),
            (&mut self.ty, self.ly),
            (&mut self.tz, self.lz),
        ] {
            if *t > l {
                *t = u64::MAX;
            }
        }
    }

    /// The leaves of this walk, from the current voxel's on (see [`LeafWalk`]).
    pub fn leaves(&self) -> LeafWalk {
        let exit = |v: i32, s: i32, t: u64, d: u64, l: u64| -> u64 {
            if s == 0 {
                return u64::MAX;
            }
            // Crossings to the leaf's face: the last of them leaves the leaf.
            let k = if s > 0 { 8 - (v & 7) } else { (v & 7) + 1 } as u64;
            kth_crossing(t, d, l, k)
        };
        LeafWalk {
            origin: crate::tree::leaf_origin(self.voxel()),
            exit: [
                exit(self.x, self.sx, self.tx, self.dx, self.lx),
                exit(self.y, self.sy, self.ty, self.dy, self.ly),
                exit(self.z, self.sz, self.tz, self.dz, self.lz),
            ],
            d8: [self.dx, self.dy, self.dz].map(|d| d.saturating_mul(8)),
            last: [self.lx, self.ly, self.lz],
            dir: [self.sx, self.sy, self.sz],
            entry: None,
        }
    }

    /// The state [`Dda::step`]s from this one reach just after the crossing at `t` on
    /// `axis` (a crossing of this walk: a [`LeafWalk::entry`]). Crossings are taken in
    /// order of `t`, ties by axis, so those made by then are each axis's crossings at
    /// `t` or before, the later axes' only before: counted with a division per axis.
    pub fn after_crossing(&self, t: u64, axis: usize) -> Dda {
        let made = |t0: u64, d: u64, last: u64, upto: bool| -> u64 {
            match (upto, t) {
                (false, 0) => 0,
                (true, _) => crossings_by(t0, d, last, t),
                (false, _) => crossings_by(t0, d, last, t - 1),
            }
        };
        self.after([
            made(self.tx, self.dx, self.lx, true),
            made(self.ty, self.dy, self.ly, axis >= 1),
            made(self.tz, self.dz, self.lz, axis >= 2),
        ])
    }

    /// The state after `made[a]` more crossings of each axis `a`: the state [`Dda::step`]s
    /// from this one reach if those are the crossings they take first (each count at most
    /// the axis's crossings left).
    #[doc(hidden)]
    pub fn after(&self, made: [u64; 3]) -> Dda {
        let [cx, cy, cz] = made;
        // After its last crossing an axis is done, as `step` marks it.
        let next = |t0: u64, d: u64, last: u64, c: u64| {
            if c == 0 {
                t0
            } else {
                kth_crossing(t0, d, last, c + 1)
            }
        };
        // Counts are at most the axis's crossings (< 2^32): no overflow.
        Dda {
            x: self.x + self.sx * cx as i32,
            y: self.y + self.sy * cy as i32,
            z: self.z + self.sz * cz as i32,
            tx: next(self.tx, self.dx, self.lx, cx),
            ty: next(self.ty, self.dy, self.ly, cy),
            tz: next(self.tz, self.dz, self.lz, cz),
            steps: self.steps - (cx + cy + cz) as u32,
            ..self.clone()
        }
    }

    /// Per axis: the next crossing (`u64::MAX` for none), between crossings, the last
    /// crossing and the direction.
    #[doc(hidden)]
    pub fn axes(&self) -> ([u64; 3], [u64; 3], [u64; 3], [i32; 3]) {
        (
            [self.tx, self.ty, self.tz],
            [self.dx, self.dy, self.dz],
            [self.lx, self.ly, self.lz],
            [self.sx, self.sy, self.sz],
        )
    }

    #[inline]
    pub fn voxel(&self) -> VoxelCoord {
        VoxelCoord::new(self.x, self.y, self.z)
    }
}

/// The `t` of an axis's `k`-th crossing (`k >= 1`; the first at `t0`, then every `d`),
/// `u64::MAX` if the axis has fewer crossings (its last at `last`).
#[inline]
#[doc(hidden)]
pub fn kth_crossing(t0: u64, d: u64, last: u64, k: u64) -> u64 {
    let t = t0.saturating_add(d.saturating_mul(k - 1));
    if t > last {
        u64::MAX
    } else {
        t
    }
}

/// How many of an axis's crossings (the first at `t0`, `u64::MAX` for none, then every
/// `d` up to `last`) come at `t` or before.
#[inline]
#[doc(hidden)]
pub fn crossings_by(t0: u64, d: u64, last: u64, t: u64) -> u64 {
    if t0 == u64::MAX || d == 0 || t0 > t.min(last) {
        0
    } else {
        (t.min(last) - t0) / d + 1
    }
}

/// The grid leaves (aligned 8x8x8 blocks of voxels) a [`Dda`] walk passes through, in
/// order, without visiting their voxels: a walk that can pass most leaves whole (a line
/// of sight over free space) steps these, and takes up the voxel walk
/// ([`Dda::after_crossing`]) only in the leaves it has to look into. Each axis keeps the
/// `t` of its next crossing out of the current leaf; the leaf is left by the first of
/// them (ties: x, y, z), as the voxel walk leaves it.
#[derive(Clone, Debug)]
pub struct LeafWalk {
    origin: VoxelCoord,
    /// `t` of each axis's crossing out of the current leaf, u64::MAX if none.
    exit: [u64; 3],
    d8: [u64; 3],
    last: [u64; 3],
    dir: [i32; 3],
    entry: Option<(u64, usize)>,
}

impl LeafWalk {
    /// Origin of the current leaf.
    #[inline]
    pub fn origin(&self) -> VoxelCoord {
        self.origin
    }

    /// The crossing (`t`, axis) that entered the current leaf; `None` in the first.
    #[inline]
    pub fn entry(&self) -> Option<(u64, usize)> {
        self.entry
    }

    /// Move to the next leaf; `false` if the current one holds the end voxel.
    #[inline]
    pub fn advance(&mut self) -> bool {
        let [ex, ey, ez] = self.exit;
        let a = if ex <= ey && ex <= ez {
            0
        } else if ey <= ez {
            1
        } else {
            2
        };
        let t = self.exit[a];
        if t == u64::MAX {
            return false;
        }
        let step = 8 * self.dir[a];
        match a {
            0 => self.origin.x += step,
            1 => self.origin.y += step,
            _ => self.origin.z += step,
        }
        let next = t.saturating_add(self.d8[a]);
        self.exit[a] = if next > self.last[a] { u64::MAX } else { next };
        self.entry = Some((t, a));
        true
    }
}

/// Visit every voxel from `floor(o)` to `floor(e)` inclusive, in order.
pub fn for_each_voxel(o: [f64; 3], e: [f64; 3], mut f: impl FnMut(VoxelCoord)) {
    let mut d = Dda::new(o, e);
    f(d.voxel());
    while d.steps() > 0 {
        d.step();
        f(d.voxel());
    }
}

/// Visit voxels from `floor(o)` towards `floor(e)` until `f` returns `Some`.
pub fn find_voxel<T>(
    o: [f64; 3],
    e: [f64; 3],
    mut f: impl FnMut(VoxelCoord) -> Option<T>,
) -> Option<T> {
    let mut d = Dda::new(o, e);
    if let Some(t) = f(d.voxel()) {
        return Some(t);
    }
    while d.steps() > 0 {
        d.step();
        if let Some(t) = f(d.voxel()) {
            return Some(t);
        }
    }
    None
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::test_rng::Rng;
    use std::collections::BTreeSet;

    fn walk(o: [f64; 3], e: [f64; 3]) -> Vec<VoxelCoord> {
        let mut v = Vec::new();
        for_each_voxel(o, e, |c| v.push(c));
        v
    }

    /// Length of the part of segment o->e inside voxel `c` (slab clipping), or None. With
    /// `open`, a segment lying in a face plane is outside the box.
    fn overlap(o: [f64; 3], e: [f64; 3], c: VoxelCoord, open: bool) -> Option<f64> {
        let (mut t0, mut t1) = (0.0f64, 1.0f64);
        let c = c.to_array();
        for a in 0..3 {
            let (lo, hi) = (c[a] as f64, c[a] as f64 + 1.0);
            let d = e[a] - o[a];
            if d == 0.0 {
                let outside = if open {
                    o[a] <= lo || o[a] >= hi
                } else {
                    o[a] < lo || o[a] > hi
                };
                if outside {
                    return None;
                }
            } else {
                let (mut ta, mut tb) = ((lo - o[a]) / d, (hi - o[a]) / d);
                if ta > tb {
                    std::mem::swap(&mut ta, &mut tb);
                }
                t0 = t0.max(ta);
                t1 = t1.min(tb);
            }
        }
        let len = ((0..3).map(|a| (e[a] - o[a]).powi(2)).sum::<f64>()).sqrt();
        (t1 >= t0).then_some((t1 - t0) * len)
    }

    /// Brute force over the bounding box: voxels the segment crosses with positive length
    /// (`strict`) or touches at all.
    fn reference(o: [f64; 3], e: [f64; 3], min_len: f64) -> BTreeSet<VoxelCoord> {
        let lo: Vec<i32> = (0..3).map(|a| o[a].min(e[a]).floor() as i32 - 1).collect();
        let hi: Vec<i32> = (0..3).map(|a| o[a].max(e[a]).floor() as i32 + 1).collect();
        let mut s = BTreeSet::new();
        for x in lo[0]..=hi[0] {
            for y in lo[1]..=hi[1] {
                for z in lo[2]..=hi[2] {
                    let c = VoxelCoord::new(x, y, z);
                    if overlap(o, e, c, min_len > 0.0).is_some_and(|l| l > min_len) {
                        s.insert(c);
                    }
                }
            }
        }
        s
    }

    fn check(o: [f64; 3], e: [f64; 3]) {
        let path = walk(o, e);
        let start = VoxelCoord::new(
            o[0].floor() as i32,
            o[1].floor() as i32,
            o[2].floor() as i32,
        );
        let end = VoxelCoord::new(
            e[0].floor() as i32,
            e[1].floor() as i32,
            e[2].floor() as i32,
        );
        assert_eq!(path[0], start);
        assert_eq!(*path.last().unwrap(), end);
        let d = end - start;
        assert_eq!(path.len() as i32, d.x.abs() + d.y.abs() + d.z.abs() + 1);
        for w in path.windows(2) {
            let s = w[1] - w[0];
            assert_eq!(
                s.x.abs() + s.y.abs() + s.z.abs(),
                1,
                "6-connected: {o:?} {e:?}"
            );
        }
        let set: BTreeSet<_> = path.iter().copied().collect();
        assert_eq!(set.len(), path.len(), "no voxel twice");
        // Every voxel crossed with positive length is visited; every visited voxel is touched.
        let strict = reference(o, e, 1e-9);
        let touched = reference(o, e, -1e-9);
        assert!(
            strict.is_subset(&set),
            "missed {:?} on {o:?}->{e:?}",
            strict.difference(&set).collect::<Vec<_>>()
        );
        assert!(
            set.is_subset(&touched),
            "extra {:?} on {o:?}->{e:?}",
            set.difference(&touched).collect::<Vec<_>>()
        );
    }

    #[test]
    fn matches_brute_force_on_random_rays() {
        let mut r = Rng(7);
        for i in 0..4000 {
            let scale = if i % 2 == 0 { 6.0 } else { 25.0 };
            let o = [r.f() * 4.0 - 2.0, r.f() * 4.0 - 2.0, r.f() * 4.0 - 2.0];
            let e = [
                o[0] + (r.f() * 2.0 - 1.0) * scale,
                o[1] + (r.f() * 2.0 - 1.0) * scale,
                o[2] + (r.f() * 2.0 - 1.0) * scale,
            ];
            check(o, e);
        }
    }

    /// Walk with `step_far` for all but the last two steps, as the integrator does.
    fn walk_far(o: [f64; 3], e: [f64; 3]) -> Vec<VoxelCoord> {
        let mut d = Dda::new(o, e);
        let mut v = vec![d.voxel()];
        while d.steps() > 2 {
            d.step_far();
            v.push(d.voxel());
        }
        d.settle();
        while d.steps() > 0 {
            d.step();
            v.push(d.voxel());
        }
        v
    }

    /// Cases 0-2 move the end just below, onto, or (on `axis`) just above voxel faces,
    /// where rounding decides; other cases leave it.
    fn near_faces(case: usize, axis: usize, e: &mut [f64; 3]) {
        match case {
            0 => *e = e.map(|c| c.round() - 1e-12),
            1 => *e = e.map(|c| c.round()),
            2 => e[axis] = e[axis].round() + 1e-13,
            _ => {}
        }
    }

    #[test]
    fn step_far_walks_the_same_voxels() {
        let mut r = Rng(11);
        for i in 0..20000 {
            let o = [0, 1, 2].map(|_| r.f() * 4.0 - 2.0);
            let mut e = [0, 1, 2].map(|k| o[k] + (r.f() * 2.0 - 1.0) * 40.0);
            near_faces(i % 4, i % 3, &mut e);
            assert_eq!(walk_far(o, e), walk(o, e), "{o:?} -> {e:?}");
        }
        // The longest rays, and rays with a tiny extent on one axis (huge delta).
        for _ in 0..2000 {
            let o = [0, 1, 2].map(|_| r.f() * 4.0 - 2.0);
            let mut e = [0, 1, 2].map(|k| o[k] + (r.f() * 2.0 - 1.0) * 4700.0);
            e[1] = o[1].floor() + 1.0 + 1e-9 * r.f();
            assert_eq!(walk_far(o, e), walk(o, e), "{o:?} -> {e:?}");
        }
    }

    /// A leaf walk passes the leaves the voxel walk passes, in order, and the state after
    /// each leaf's entry crossing is the one `step`s reach on entering it.
    #[test]
    fn leaf_walks_follow_the_voxel_walk() {
        let mut r = Rng(23);
        let mut entries = 0;
        for i in 0..6000 {
            let o = [0, 1, 2].map(|_| r.f() * 16.0 - 8.0);
            let mut e = [0, 1, 2].map(|k| o[k] + (r.f() * 2.0 - 1.0) * 60.0);
            near_faces(i % 7, i % 3, &mut e);
            match i % 7 {
                3 => e[i % 3] = o[i % 3],
                4 => {
                    // Lattice rays: exact edge and corner crossings, where ties decide.
                    let q = |r: &mut Rng| ((r.f() * 64.0).floor() - 32.0) / 2.0;
                    let o2 = [q(&mut r), q(&mut r), q(&mut r)];
                    let e2 = [q(&mut r), q(&mut r), q(&mut r)];
                    entries += check_leaves(o2, e2);
                    continue;
                }
                // One face crossing on y, at t just below 1: a delta near the u64 limit.
                5 => e[1] = o[1].floor() + 1.0 + 1e-9 * r.f(),
                _ => {}
            }
            entries += check_leaves(o, e);
        }
        assert!(entries > 50_000, "only {entries} leaf entries checked");
    }

    fn check_leaves(o: [f64; 3], e: [f64; 3]) -> u32 {
        let start = Dda::new(o, e);
        // The voxel walk's state on entering each leaf.
        let mut d = start.clone();
        let mut want = vec![d.clone()];
        while d.steps() > 0 {
            d.step();
            if d.voxel().shr(3) != want.last().unwrap().voxel().shr(3) {
                want.push(d.clone());
            }
        }
        let mut leaves = start.leaves();
        let mut got = vec![start.clone()];
        assert_eq!(leaves.origin(), start.voxel().shr(3).shl(3));
        while leaves.advance() {
            let (t, axis) = leaves.entry().unwrap();
            let at = start.after_crossing(t, axis);
            assert_eq!(leaves.origin(), at.voxel().shr(3).shl(3), "{o:?} -> {e:?}");
            got.push(at);
        }
        assert_eq!(got, want, "{o:?} -> {e:?}");
        got.len() as u32 - 1
    }

    #[test]
    fn matches_brute_force_on_lattice_rays() {
        // Origins and ends on voxel corners, faces and centres: the tie-heavy cases.
        let mut r = Rng(99);
        for _ in 0..3000 {
            let q = |r: &mut Rng| ((r.f() * 24.0).floor() - 12.0) / 2.0;
            let o = [q(&mut r), q(&mut r), q(&mut r)];
            let e = [q(&mut r), q(&mut r), q(&mut r)];
            check(o, e);
        }
    }

    #[test]
    fn degenerate_rays() {
        assert_eq!(
            walk([0.5, 0.5, 0.5], [0.5, 0.5, 0.5]),
            vec![VoxelCoord::new(0, 0, 0)]
        );
        assert_eq!(
            walk([0.1, 0.2, 0.3], [0.9, 0.8, 0.7]),
            vec![VoxelCoord::new(0, 0, 0)]
        );
        // Axis-aligned, negative direction.
        let p = walk([0.5, 0.5, 0.5], [-2.5, 0.5, 0.5]);
        assert_eq!(
            p,
            (-3..=0)
                .rev()
                .map(|x| VoxelCoord::new(x, 0, 0))
                .collect::<Vec<_>>()
        );
        // Exact diagonal through corners: ties go x, then y, then z.
        let p = walk([0.5, 0.5, 0.5], [2.5, 2.5, 2.5]);
        assert_eq!(p.len(), 7);
        assert_eq!(
            &p[..4],
            &[
                VoxelCoord::new(0, 0, 0),
                VoxelCoord::new(1, 0, 0),
                VoxelCoord::new(1, 1, 0),
                VoxelCoord::new(1, 1, 1)
            ]
        );
        // Entirely in negative coordinates.
        check([-10.3, -20.7, -5.5], [-30.1, -2.2, -5.5]);
        assert_eq!(
            walk([-0.5, -0.5, -0.5], [-0.5, -0.5, -0.5]),
            vec![VoxelCoord::new(-1, -1, -1)]
        );
    }

    #[test]
    fn find_voxel_stops_early() {
        let hit = find_voxel([0.5, 0.5, 0.5], [10.5, 0.5, 0.5], |v| {
            (v.x == 4).then_some(v)
        });
        assert_eq!(hit, Some(VoxelCoord::new(4, 0, 0)));
        assert_eq!(
            find_voxel([0.5, 0.5, 0.5], [3.5, 0.5, 0.5], |v| (v.x == 4)
                .then_some(v)),
            None
        );
    }
}

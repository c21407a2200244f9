//! The exact distance transform of one patch of 32³ voxels: the separable transform of
//! Saito and Toriwaki (one axis at a time, each pass a lower envelope of parabolas), cut to
//! the band, on a dense copy of the obstacles within `radius` of the patch.
//!
//! Each cell carries a `u32` key that orders candidates by squared distance first and then
//! by offset, so that the minimum of keys is the nearest obstacle with a fixed tie-break:
//!
//! ```text
//! bits 15..28  d², voxels² (< 2 * 63²)
//! bits  8..15  dx + 64
//! bits  1..8   dy + 64
//! bit   0      obstacle above (dz > 0)
//! ```
//!
//! `|dz|` is not stored: it follows from d², dx and dy. A pass adds its axis's `d²` and
//! offset to the previous pass's keys, which left that offset field zero, and takes the
//! minimum over the offsets within the radius: the minimum over all obstacles of the
//! whole key, as the three minima nest. Keys at or above `far` (`radius² << 15`) are
//! outside the band and are clamped to `far` after each pass, so the sums never reach bit
//! 28. The passes are plain loops over contiguous rows that the compiler vectorizes; the
//! caller compiles them a second time for AVX2.

use super::{UnknownPolicy, MAX_RADIUS};
use crate::coord::VoxelCoord;
use crate::grid::{Grid, Leaf};
use crate::kernel::Kernels;
use crate::mask::Mask512;

/// log2 of a patch's edge in voxels.
pub(super) const PATCH_LOG2: u32 = 5;
/// A patch's edge in voxels.
pub(super) const PATCH: usize = 1 << PATCH_LOG2;

const D2_SHIFT: u32 = 15;

/// The key of the region outside the band.
#[inline]
pub(super) fn far_key(radius: u32) -> u32 {
    (radius * radius) << D2_SHIFT
}

#[inline]
fn add_y(dy: i32) -> u32 {
    ((dy * dy) as u32) << D2_SHIFT | ((dy + 64) as u32) << 1
}

#[inline]
fn add_x(dx: i32) -> u32 {
    ((dx * dx) as u32) << D2_SHIFT | ((dx + 64) as u32) << 8
}

/// `ROOTS[k * k] = k` for k < 64 (the squares a key's |dz|² can be).
static ROOTS: [u8; 4096] = {
    let mut t = [0u8; 4096];
    let mut k = 0;
    while k < 64 {
        t[k * k] = k as u8;
        k += 1;
    }
    t
};

/// The offset to the nearest obstacle of a key inside the band.
#[inline]
pub(super) fn decode(key: u32) -> [i8; 3] {
    let d2 = (key >> D2_SHIFT) as i32;
    let dx = ((key >> 8) & 127) as i32 - 64;
    let dy = ((key >> 1) & 127) as i32 - 64;
    let dz2 = (d2 - dx * dx - dy * dy).clamp(0, 4095) as usize;
    let dz = i32::from(ROOTS[dz2]);
    let dz = if key & 1 != 0 { dz } else { -dz };
    [dx as i8, dy as i8, dz as i8]
}

/// The obstacles of a map leaf under a policy.
#[inline]
pub(super) fn obstacles(leaf: &Leaf<i8>, policy: UnknownPolicy) -> Mask512 {
    super::obstacles(&leaf.active, &leaf.marked, policy)
}

/// The obstacles of a voxel no leaf holds (unknown).
pub(super) fn absent_obstacles(policy: UnknownPolicy) -> Mask512 {
    match policy {
        UnknownPolicy::Free => Mask512::EMPTY,
        UnknownPolicy::Occupied => Mask512::FULL,
    }
}

/// Per-thread buffers of the transform, reused from patch to patch.
#[derive(Default)]
pub(crate) struct Scratch {
    obs: Vec<u8>,
    run: Vec<u8>,
    below: Vec<u8>,
    keyz: Vec<u32>,
    keyy: Vec<u32>,
    /// Per row of `keyz`: whether any key is in the band.
    live: Vec<bool>,
    /// The result: keys of the patch's voxels, x fastest, then y, then z.
    pub(super) keys: Vec<u32>,
}

/// A box of a patch's voxels, `(lo, hi)` per axis x, y, z, hi exclusive.
pub(crate) type Region = ([usize; 3], [usize; 3]);

/// Transform the patch with minimum corner `origin` (a multiple of [`PATCH`]) where it is
/// needed: fills `scratch.keys` for the voxels of `region` (their whole rows along x).
/// Returns false, leaving the keys unset, when no obstacle lies within the radius of the
/// patch (every key would be far).
pub(super) fn transform(
    scratch: &mut Scratch,
    map: &Grid<i8>,
    policy: UnknownPolicy,
    origin: VoxelCoord,
    radius: u32,
    kernels: &Kernels,
    region: Region,
) -> bool {
    let (r, t) = (radius as usize, PATCH);
    let n = t + 2 * r;
    if !fill_obstacles(&mut scratch.obs, map, policy, origin, radius) {
        return false;
    }
    scratch.run.resize(n * n, 0);
    scratch.below.resize(t * n * n, 0);
    scratch.keyz.resize(t * n * n, 0);
    scratch.keyy.resize(t * t * n, 0);
    scratch.keys.resize(t * t * t, 0);
    (kernels.field_passes)(scratch, n, r, region);
    true
}

/// Write the obstacles of the region `origin - radius .. origin + PATCH + radius` as one
/// byte per voxel (x fastest); false when there is none.
fn fill_obstacles(
    obs: &mut Vec<u8>,
    map: &Grid<i8>,
    policy: UnknownPolicy,
    origin: VoxelCoord,
    radius: u32,
) -> bool {
    let r = radius as i32;
    let n = PATCH as i32 + 2 * r;
    let g0 = VoxelCoord::new(origin.x - r, origin.y - r, origin.z - r);
    let absent = absent_obstacles(policy);
    obs.clear();
    obs.resize((n * n * n) as usize, u8::from(absent != Mask512::EMPTY));
    let mut any = absent != Mask512::EMPTY;
    let lo = |c: i32| c & !7;
    for lz in (lo(g0.z)..g0.z + n).step_by(8) {
        for ly in (lo(g0.y)..g0.y + n).step_by(8) {
            for lx in (lo(g0.x)..g0.x + n).step_by(8) {
                let o = VoxelCoord::new(lx, ly, lz);
                let Some(i) = map.leaf_index(o) else { continue };
                let m = obstacles(map.leaf(i), policy);
                if m == absent {
                    continue;
                }
                any |= !m.is_empty();
                // The leaf's voxels inside the region, per axis.
                let span = |o: i32, g: i32| ((g - o).max(0), (g + n - o).min(8));
                let (x0, x1) = span(o.x, g0.x);
                let (y0, y1) = span(o.y, g0.y);
                let (z0, z1) = span(o.z, g0.z);
                for z in z0..z1 {
                    let word = m.words[z as usize];
                    for y in y0..y1 {
                        let row = (word >> (8 * y)) as u8;
                        // The row's first voxel may lie before the region (x0 > 0 then).
                        let at = ((o.z + z - g0.z) * n + (o.y + y - g0.y)) * n + o.x - g0.x;
                        for x in x0..x1 {
                            obs[(at + x) as usize] = (row >> x) & 1;
                        }
                    }
                }
            }
        }
    }
    any
}

/// The three passes over a filled scratch (`n = PATCH + 2r`). Written as loops over
/// fixed-length rows with no branches, so that each inlined copy vectorizes.
#[inline(always)]
pub(crate) fn passes(s: &mut Scratch, n: usize, r: usize, b: Region) {
    let t = PATCH;
    let ([_, y0, z0], [_, y1, z1]) = b;
    let plane = n * n;
    let cap = (r + 1) as u8;
    let far = far_key(r as u32);
    let Scratch {
        obs,
        run,
        below,
        keyz,
        keyy,
        keys,
        live,
    } = s;
    // Along z: per column, the distance to the nearest obstacle at or below z (capped at
    // r + 1), then at or above; only the patch's planes are kept, for all of the region's
    // x and y.
    let run = &mut run[..plane];
    run.fill(cap);
    for z in 0..r + z1 {
        step(run, &obs[z * plane..][..plane], cap);
        if z >= r + z0 {
            below[(z - r) * plane..][..plane].copy_from_slice(run);
        }
    }
    run.fill(cap);
    for z in (r + z0..n).rev() {
        step(run, &obs[z * plane..][..plane], cap);
        if z < r + z1 {
            let zt = z - r;
            let out = &mut keyz[zt * plane..][..plane];
            let down = &below[zt * plane..][..plane];
            z_keys(out, down, run, far);
        }
    }
    // Rows (along x) of the z pass with any key in the band: the others add nothing.
    live.clear();
    live.resize(t * n, false);
    for (l, row) in live[z0 * n..z1 * n]
        .iter_mut()
        .zip(keyz[z0 * plane..z1 * plane].chunks_exact(n))
    {
        *l = row.iter().fold(far, |m, &k| m.min(k)) < far;
    }
    // Along y: for the patch's (y, z), every x of the region, 32 x at a time held in
    // registers over the rows with anything in the band (listed once per output row).
    const LANES: usize = 32;
    let mut rows = [(0usize, 0u32); 2 * MAX_RADIUS as usize + 1];
    for zt in z0..z1 {
        for yt in y0..y1 {
            let mut m = 0;
            for k in 0..=2 * r {
                if live[zt * n + yt + k] {
                    rows[m] = ((zt * n + yt + k) * n, add_y(k as i32 - r as i32));
                    m += 1;
                }
            }
            let rows = &rows[..m];
            let out = &mut keyy[(zt * t + yt) * n..][..n];
            let mut c0 = 0;
            while c0 + LANES <= n {
                let mut acc = [far; LANES];
                for &(at, c) in rows {
                    let src: &[u32; LANES] = keyz[at + c0..at + c0 + LANES].try_into().expect("32");
                    for i in 0..LANES {
                        acc[i] = acc[i].min(src[i] + c);
                    }
                }
                out[c0..c0 + LANES].copy_from_slice(&acc);
                c0 += LANES;
            }
            while c0 + 8 <= n {
                let mut acc = [far; 8];
                for &(at, c) in rows {
                    let src: &[u32; 8] = keyz[at + c0..at + c0 + 8].try_into().expect("8");
                    for i in 0..8 {
                        acc[i] = acc[i].min(src[i] + c);
                    }
                }
                out[c0..c0 + 8].copy_from_slice(&acc);
                c0 += 8;
            }
            out[c0..].fill(far);
            for &(at, c) in rows {
                let src = &keyz[at + c0..at + n];
                for (o, &k) in out[c0..].iter_mut().zip(src) {
                    *o = (*o).min(k + c);
                }
            }
            for o in out.iter_mut() {
                *o = (*o).min(far);
            }
        }
    }
    // Along x: the patch's voxels, a row of PATCH at a time in registers; rows with nothing
    // in the band stay far.
    for row in (z0..z1).flat_map(|z| (y0..y1).map(move |y| z * t + y)) {
        let src = &keyy[row * n..][..n];
        let mut acc = [far; PATCH];
        if src.iter().fold(far, |m, &k| m.min(k)) < far {
            for k in 0..=2 * r {
                let c = add_x(k as i32 - r as i32);
                let s: &[u32; PATCH] = src[k..k + PATCH].try_into().expect("n >= PATCH + 2r");
                for i in 0..PATCH {
                    acc[i] = acc[i].min(s[i] + c);
                }
            }
        }
        keys[row * t..][..t].copy_from_slice(&acc);
    }
}

/// Keys of one plane from the distances below and above, sixteen at a time.
#[inline(always)]
fn z_keys(out: &mut [u32], below: &[u8], above: &[u8], far: u32) {
    let key = |b: u8, a: u8| {
        let (b, a) = (u32::from(b), u32::from(a));
        ((b * b) << D2_SHIFT).min((a * a) << D2_SHIFT | 1).min(far)
    };
    let mut o = out.chunks_exact_mut(16);
    let mut d = below.chunks_exact(16);
    let mut u = above.chunks_exact(16);
    for ((o, d), u) in (&mut o).zip(&mut d).zip(&mut u) {
        let (o, d, u): (&mut [u32; 16], &[u8; 16], &[u8; 16]) = (
            o.try_into().expect("16"),
            d.try_into().expect("16"),
            u.try_into().expect("16"),
        );
        for i in 0..16 {
            o[i] = key(d[i], u[i]);
        }
    }
    for ((o, &d), &u) in o
        .into_remainder()
        .iter_mut()
        .zip(d.remainder())
        .zip(u.remainder())
    {
        *o = key(d, u);
    }
}

/// One plane of the z sweep: a column's count goes up by one (to `cap`) and back to 0 on
/// an obstacle (`o` is 0 or 1).
#[inline(always)]
fn step(run: &mut [u8], o: &[u8], cap: u8) {
    let o = &o[..run.len()];
    for i in 0..run.len() {
        run[i] = (run[i] + 1).min(cap) & o[i].wrapping_sub(1);
    }
}

/// [`passes`] compiled for AVX2: eight keys per instruction instead of four.
///
/// # Safety
/// The CPU must have AVX2 (`Kernel::Avx2.supported()` checks it).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
pub(crate) unsafe fn passes_avx2(s: &mut Scratch, n: usize, r: usize, b: Region) {
    passes(s, n, r, b)
}

/// [`passes`] compiled for AVX-512: sixteen keys per instruction.
///
/// # Safety
/// The CPU must have AVX-512 F and BW (`Kernel::Avx512.supported()` checks them).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512bw")]
pub(crate) unsafe fn passes_avx512(s: &mut Scratch, n: usize, r: usize, b: Region) {
    passes(s, n, r, b)
}

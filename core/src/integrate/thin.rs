//! The paper's trade-off modes ([`RayMode`] other than `Exact`): fewer rays for a coarser
//! map. Each keeps the first ray of a kind in scan order, so its result does not depend on
//! the thread count.

use super::prepare::{direction_key, set_direction_keys, Ray};
use super::RayMode;
use hashbrown::HashSet;
use rayon::prelude::*;

/// Drop (or merge) the rays that `mode` trades for speed.
pub(super) fn thin_out(rays: &mut Vec<Ray>, origin: [f64; 3], mode: RayMode) {
    match mode {
        RayMode::Exact => {}
        RayMode::Subsample { factor } => {
            let f = f64::from(factor);
            let mut seen = HashSet::with_capacity(rays.len());
            rays.retain(|r| {
                let c = r.end.map(|c| (c * f).floor() as i64);
                seen.insert((c, r.hit))
            });
        }
        RayMode::UniqueEnd => {
            let mut seen = HashSet::with_capacity(rays.len());
            rays.retain_mut(|r| {
                let v = r.end.map(f64::floor);
                r.end = v.map(|c| c + 0.5);
                seen.insert((v.map(|c| c as i64), r.hit))
            });
        }
        RayMode::Bundle { threshold } => {
            let vox = |r: &Ray| (r.end.map(|c| c.floor() as i64), r.hit);
            set_direction_keys(rays, origin);
            rays.par_sort_unstable_by_key(|r| (vox(r), r.key));
            let mut out = Vec::with_capacity(rays.len());
            let mut i = 0;
            while i < rays.len() {
                let k = vox(&rays[i]);
                let n = rays[i..].iter().take_while(|r| vox(r) == k).count();
                let group = &rays[i..i + n];
                if n > threshold as usize {
                    let mut m = [0.0; 3];
                    for r in group {
                        (0..3).for_each(|a| m[a] += r.end[a]);
                    }
                    let end = m.map(|c| c / n as f64);
                    let d = [end[0] - origin[0], end[1] - origin[1], end[2] - origin[2]];
                    out.push(Ray::new(end, direction_key(d), group[0].hit));
                } else {
                    out.extend_from_slice(group);
                }
                i += n;
            }
            *rays = out;
        }
    }
}

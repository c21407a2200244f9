//! The long-mission benchmark's world: a procedural city of blocks on a 48 m grid
//! (buildings of varied footprint and height, street poles, parked cars, a ground plane),
//! as large as asked, and a route along its streets that returns to its start.
//!
//! Each block's boxes are made from a hash of its grid index, so any block is the same
//! whenever it is asked for, and a ray (at most 30 m, under a block's pitch) tests the
//! boxes of the few blocks its footprint overlaps only.

use super::{first_hit, Aabb, Surfaces};
use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
use std::sync::Mutex;

/// Block pitch (m): a 36 m block and a 12 m street.
pub const PITCH: f64 = 48.0;
const STREET: f64 = 12.0;

/// A block's boxes, shared by the rays that test them.
type Block = std::sync::Arc<Vec<Aabb>>;

/// The city: blocks made on demand and kept.
pub struct City {
    seed: u64,
    blocks: Mutex<std::collections::HashMap<(i64, i64), Block>>,
}

fn hash(seed: u64, a: i64, b: i64, k: u64) -> u64 {
    let mut x = seed
        ^ (a as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15)
        ^ (b as u64).wrapping_mul(0xC2B2_AE3D_27D4_EB4F)
        ^ k.wrapping_mul(0x1656_67B1_9E37_79F9);
    x ^= x >> 33;
    x = x.wrapping_mul(0xFF51_AFD7_ED55_8CCD);
    x ^= x >> 33;
    x = x.wrapping_mul(0xC4CE_B9FE_1A85_EC53);
    x ^ (x >> 33)
}

/// A uniform number in [lo, hi) from a hash.
fn unit(h: u64, lo: f64, hi: f64) -> f64 {
    lo + (hi - lo) * (h >> 11) as f64 / (1u64 << 53) as f64
}

impl City {
    pub fn new(seed: u64) -> Self {
        Self {
            seed,
            blocks: Mutex::new(Default::default()),
        }
    }

    /// The boxes of block (i, j), whose streets run along x = i * PITCH and y = j * PITCH.
    fn block(&self, i: i64, j: i64) -> Block {
        let mut blocks = self.blocks.lock().unwrap_or_else(|e| e.into_inner());
        blocks
            .entry((i, j))
            .or_insert_with(|| std::sync::Arc::new(self.make_block(i, j)))
            .clone()
    }

    fn make_block(&self, i: i64, j: i64) -> Vec<Aabb> {
        let h = |k: u64| hash(self.seed, i, j, k);
        let (x0, y0) = (
            i as f64 * PITCH + STREET / 2.0,
            j as f64 * PITCH + STREET / 2.0,
        );
        let side = PITCH - STREET;
        let mut b = Vec::new();
        // Buildings: the block cut into 1 to 3 lots along x and y, each built or a yard.
        let (nx, ny) = (1 + h(1) % 3, 1 + h(2) % 3);
        for a in 0..nx {
            for c in 0..ny {
                let k = 10 + a * 3 + c;
                if h(k) % 5 == 0 {
                    continue; // a yard
                }
                let (lx, ly) = (side / nx as f64, side / ny as f64);
                let inset = unit(h(k + 100), 1.0, 3.0);
                let height = unit(h(k + 200), 4.0, 28.0);
                b.push(Aabb::new(
                    [x0 + a as f64 * lx + inset, y0 + c as f64 * ly + inset, 0.0],
                    [
                        x0 + (a + 1) as f64 * lx - inset,
                        y0 + (c + 1) as f64 * ly - inset,
                        height,
                    ],
                ));
            }
        }
        // Poles along the block's two street sides nearest the origin, every 12 m.
        for p in 0..3 {
            let t = 6.0 + 12.0 * p as f64;
            for (px, py) in [(x0 + t, y0 - 0.6), (x0 - 0.6, y0 + t)] {
                b.push(Aabb::new(
                    [px - 0.15, py - 0.15, 0.0],
                    [px + 0.15, py + 0.15, 4.5],
                ));
            }
        }
        // Parked cars along the curb.
        for car in 0..(h(3) % 4) {
            let t = unit(h(30 + car), 2.0, side - 6.0);
            let (cx, cy) = (x0 + t, y0 - 2.2);
            b.push(Aabb::new([cx, cy - 0.9, 0.0], [cx + 4.5, cy + 0.9, 1.5]));
        }
        b
    }
}

impl Surfaces for City {
    fn cast(&self, o: &[f64; 3], d: &[f64; 3], max: f64) -> Option<f64> {
        let inv = d.map(|c| 1.0 / c);
        // The ground plane, z = 0.
        let mut best = (d[2] < 0.0).then(|| -o[2] / d[2]).filter(|&t| t > 0.0);
        let end = [o[0] + max * d[0], o[1] + max * d[1]];
        let cell = |v: f64| (v / PITCH).floor() as i64;
        let (i0, i1) = (cell(o[0].min(end[0])), cell(o[0].max(end[0])));
        let (j0, j1) = (cell(o[1].min(end[1])), cell(o[1].max(end[1])));
        for i in i0..=i1 {
            for j in j0..=j1 {
                if let Some(t) = first_hit(&self.block(i, j), o, &inv) {
                    best = Some(best.map_or(t, |b: f64| b.min(t)));
                }
            }
        }
        best.filter(|&t| t <= max)
    }
}

/// The route: around a rectangle of `blocks` x `blocks` blocks along the streets,
/// starting and ending at the origin, a sensor `height` m above the ground facing along
/// the street. Its length is 4 * blocks * PITCH.
pub struct Route {
    pub blocks: u32,
    pub height: f64,
}

impl Route {
    pub fn length(&self) -> f64 {
        4.0 * f64::from(self.blocks) * PITCH
    }

    /// The pose after `s` metres (wrapping at the end).
    pub fn pose(&self, s: f64) -> Isometry3<f64> {
        let side = f64::from(self.blocks) * PITCH;
        let s = s.rem_euclid(self.length());
        let (leg, t) = ((s / side).floor() as u32, s % side);
        let (x, y, heading) = match leg {
            0 => (t, 0.0, 0.0),
            1 => (side, t, 90.0),
            2 => (side - t, side, 180.0),
            _ => (0.0, side - t, 270.0),
        };
        Isometry3::from_parts(
            Translation3::new(x, y, self.height),
            UnitQuaternion::from_axis_angle(&Vector3::z_axis(), f64::to_radians(heading)),
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_route_closes_on_open_street_and_sees_buildings() {
        let city = City::new(7);
        let r = Route {
            blocks: 8,
            height: 1.8,
        };
        assert!(r.length() >= 1500.0);
        let (a, b) = (r.pose(0.0), r.pose(r.length()));
        assert!((a.translation.vector - b.translation.vector).norm() < 1e-9);
        let mut hits = 0;
        for k in 0..200 {
            let p = r.pose(k as f64 * r.length() / 200.0);
            let o: [f64; 3] = p.translation.vector.into();
            // Nothing solid at the sensor: straight up is open sky or a far roof.
            assert!(
                city.cast(&o, &[0.0, 0.0, 1.0], 0.5).is_none(),
                "inside a box at {o:?}"
            );
            for az in 0..8 {
                let a = f64::from(az) * std::f64::consts::FRAC_PI_4;
                let d = [a.cos() * 0.99, a.sin() * 0.99, -0.141];
                let n = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
                if let Some(t) = city.cast(&o, &d.map(|c| c / n), 30.0) {
                    assert!(t > 0.3, "a surface {t} m from the sensor at {o:?}");
                    hits += 1;
                }
            }
        }
        assert!(hits > 1000, "{hits}");
    }
}

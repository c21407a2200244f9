//! A procedural indoor scene and a simulated spinning LiDAR moving through it, for the
//! demo: four rooms with doors, furniture, floor and ceiling, all axis-aligned boxes.
//! [`city`] holds the long-mission benchmark's outdoor scene and route.

pub mod city;

use crate::rng::XorShift;
use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};

/// An axis-aligned box, metres.
#[derive(Clone, Copy, Debug)]
pub struct Aabb {
    pub min: [f64; 3],
    pub max: [f64; 3],
}

impl Aabb {
    pub fn new(min: [f64; 3], max: [f64; 3]) -> Self {
        Self { min, max }
    }

    /// Entry distance of the ray `o + t d` (t > 0), if it hits from outside.
    #[inline]
    fn hit(&self, o: &[f64; 3], inv_d: &[f64; 3]) -> Option<f64> {
        let (mut t0, mut t1) = (0.0f64, f64::INFINITY);
        for k in 0..3 {
            let a = (self.min[k] - o[k]) * inv_d[k];
            let b = (self.max[k] - o[k]) * inv_d[k];
            t0 = t0.max(a.min(b));
            t1 = t1.min(a.max(b));
        }
        (t0 <= t1 && t0 > 0.0).then_some(t0)
    }

    #[cfg(test)]
    fn contains(&self, p: &[f64; 3]) -> bool {
        (0..3).all(|k| self.min[k] <= p[k] && p[k] <= self.max[k])
    }
}

/// A scene a LiDAR can see: the distance to the first surface along a ray.
pub trait Surfaces {
    /// Distance to the first surface along unit direction `d` from `o`, up to `max`.
    fn cast(&self, o: &[f64; 3], d: &[f64; 3], max: f64) -> Option<f64>;
}

impl Surfaces for Scene {
    fn cast(&self, o: &[f64; 3], d: &[f64; 3], max: f64) -> Option<f64> {
        Scene::cast(self, o, d, max)
    }
}

/// The nearest entry into any of `boxes` along `o + t d` (`inv_d` = 1 / d).
fn first_hit(boxes: &[Aabb], o: &[f64; 3], inv_d: &[f64; 3]) -> Option<f64> {
    boxes
        .iter()
        .filter_map(|b| b.hit(o, inv_d))
        .fold(None, |m: Option<f64>, t| Some(m.map_or(t, |m| m.min(t))))
}

/// The scene: solid boxes.
pub struct Scene {
    pub boxes: Vec<Aabb>,
}

const WALL: f64 = 0.2;
const CEILING: f64 = 2.6;

impl Scene {
    /// Four rooms in a 16 m x 10 m building: walls 0.2 m thick with 1 m doors, a floor,
    /// a ceiling at 2.6 m, tables on legs, shelves, boxes and a pillar.
    pub fn indoor() -> Self {
        let (w, h) = (16.0, 10.0);
        let mut b = Vec::new();
        let wall_x = |b: &mut Vec<Aabb>, x: f64, y0: f64, y1: f64| {
            b.push(Aabb::new(
                [x - WALL / 2.0, y0, 0.0],
                [x + WALL / 2.0, y1, CEILING],
            ))
        };
        let wall_y = |b: &mut Vec<Aabb>, y: f64, x0: f64, x1: f64| {
            b.push(Aabb::new(
                [x0, y - WALL / 2.0, 0.0],
                [x1, y + WALL / 2.0, CEILING],
            ))
        };
        // Floor and ceiling slabs.
        b.push(Aabb::new([-0.5, -0.5, -0.2], [w + 0.5, h + 0.5, 0.0]));
        b.push(Aabb::new(
            [-0.5, -0.5, CEILING],
            [w + 0.5, h + 0.5, CEILING + 0.2],
        ));
        // Outer walls.
        wall_x(&mut b, 0.0, 0.0, h);
        wall_x(&mut b, w, 0.0, h);
        wall_y(&mut b, 0.0, 0.0, w);
        wall_y(&mut b, h, 0.0, w);
        // Interior walls with 1 m doors: x = 6 (door y 4..5), x = 11 (door y 6..7),
        // y = 5 between x = 11 and 16 (door x 13..14).
        wall_x(&mut b, 6.0, 0.0, 4.0);
        wall_x(&mut b, 6.0, 5.0, h);
        wall_x(&mut b, 11.0, 0.0, 6.0);
        wall_x(&mut b, 11.0, 7.0, h);
        wall_y(&mut b, 5.0, 11.0, 13.0);
        wall_y(&mut b, 5.0, 14.0, w);
        // Furniture.
        let table = |b: &mut Vec<Aabb>, x: f64, y: f64, lx: f64, ly: f64| {
            b.push(Aabb::new([x, y, 0.72], [x + lx, y + ly, 0.76]));
            for (dx, dy) in [
                (0.0, 0.0),
                (lx - 0.06, 0.0),
                (0.0, ly - 0.06),
                (lx - 0.06, ly - 0.06),
            ] {
                b.push(Aabb::new(
                    [x + dx, y + dy, 0.0],
                    [x + dx + 0.06, y + dy + 0.06, 0.72],
                ));
            }
        };
        table(&mut b, 1.0, 7.5, 1.8, 0.9);
        table(&mut b, 8.0, 1.0, 1.6, 1.6);
        table(&mut b, 12.5, 7.8, 2.0, 1.0);
        // Shelves along walls, a pillar, boxes.
        b.push(Aabb::new([0.1, 1.0, 0.0], [0.5, 3.5, 2.0]));
        b.push(Aabb::new([7.5, 9.4, 0.0], [10.5, 9.9, 1.8]));
        b.push(Aabb::new([15.4, 0.5, 0.0], [15.9, 3.0, 2.2]));
        b.push(Aabb::new([8.3, 6.8, 0.0], [8.7, 7.2, CEILING]));
        b.push(Aabb::new([4.0, 0.6, 0.0], [4.8, 1.4, 0.6]));
        b.push(Aabb::new([4.1, 0.7, 0.6], [4.7, 1.3, 1.0]));
        b.push(Aabb::new([12.0, 1.0, 0.0], [13.0, 1.6, 0.9]));
        b.push(Aabb::new([2.5, 4.3, 0.0], [3.5, 5.2, 0.45]));
        Self { boxes: b }
    }

    /// Distance to the first surface along unit direction `d` from `o`, up to `max`.
    pub fn cast(&self, o: &[f64; 3], d: &[f64; 3], max: f64) -> Option<f64> {
        let inv = d.map(|c| 1.0 / c);
        first_hit(&self.boxes, o, &inv).filter(|&t| t <= max)
    }

    /// Is `p` inside any solid?
    #[cfg(test)]
    fn solid(&self, p: &[f64; 3]) -> bool {
        self.boxes.iter().any(|b| b.contains(p))
    }
}

/// A path through all four rooms (x, y waypoints, metres), clear of furniture.
pub const PATH: [[f64; 2]; 10] = [
    [2.0, 2.5],
    [3.0, 6.0],
    [5.0, 4.5],
    [7.5, 4.5],
    [9.5, 5.5],
    [11.0, 6.5],
    [13.5, 6.2],
    [13.5, 3.8],
    [14.0, 2.0],
    [12.5, 3.5],
];

/// Pose on the path after travelling `s` metres (sensor at `height`, facing along the
/// path), clamped to the path's end.
pub fn pose_along(s: f64, height: f64) -> Isometry3<f64> {
    let mut left = s.max(0.0);
    let n = PATH.len() - 1;
    for (i, w) in PATH.windows(2).enumerate() {
        let (a, b) = (w[0], w[1]);
        let (dx, dy) = (b[0] - a[0], b[1] - a[1]);
        let len = dx.hypot(dy);
        if left <= len || i + 1 == n {
            let f = (left / len).min(1.0);
            return Isometry3::from_parts(
                Translation3::new(a[0] + f * dx, a[1] + f * dy, height),
                UnitQuaternion::from_axis_angle(&Vector3::z_axis(), dy.atan2(dx)),
            );
        }
        left -= len;
    }
    unreachable!("PATH has at least two waypoints")
}

pub fn path_length() -> f64 {
    PATH.windows(2)
        .map(|w| (w[1][0] - w[0][0]).hypot(w[1][1] - w[0][1]))
        .sum()
}

/// A spinning LiDAR (Ouster OS0-64-like: 64 beams over +-45 degrees, 1024 columns):
/// 65,536 rays per scan, 1 cm Gaussian range noise, no point where nothing is hit.
pub struct Lidar {
    pub beams: usize,
    pub columns: usize,
    pub max_range: f64,
    pub noise_m: f64,
    dirs: Vec<[f64; 3]>,
}

impl Lidar {
    pub fn os0_64() -> Self {
        let (beams, columns, fov_deg) = (64, 1024, 90.0);
        let mut dirs = Vec::with_capacity(beams * columns);
        for c in 0..columns {
            let az = c as f64 / columns as f64 * std::f64::consts::TAU;
            for r in 0..beams {
                let el = (fov_deg / 2.0 - fov_deg * r as f64 / (beams - 1) as f64).to_radians();
                dirs.push([el.cos() * az.cos(), el.cos() * az.sin(), el.sin()]);
            }
        }
        Self {
            beams,
            columns,
            max_range: 50.0,
            noise_m: 0.01,
            dirs,
        }
    }

    /// One scan from `pose`: points in the sensor frame, appended to `out` (cleared first).
    pub fn scan(
        &self,
        scene: &impl Surfaces,
        pose: &Isometry3<f64>,
        rng: &mut XorShift,
        out: &mut Vec<[f32; 3]>,
    ) {
        out.clear();
        let o: [f64; 3] = pose.translation.vector.into();
        for d in &self.dirs {
            let w = pose.rotation * Vector3::from(*d);
            if let Some(t) = scene.cast(&o, &[w.x, w.y, w.z], self.max_range) {
                let r = t + self.noise_m * rng.gaussian();
                out.push(d.map(|c| (c * r) as f32));
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn path_is_clear_and_scans_hit_the_rooms() {
        let scene = Scene::indoor();
        let len = path_length();
        let mut s = 0.0;
        while s <= len {
            let p = pose_along(s, 0.8);
            assert!(
                !scene.solid(&p.translation.vector.into()),
                "path blocked at {s}"
            );
            s += 0.05;
        }
        let lidar = Lidar::os0_64();
        let mut pts = Vec::new();
        let pose = pose_along(1.0, 0.8);
        lidar.scan(&scene, &pose, &mut XorShift::new(1), &mut pts);
        // A closed building: every ray hits something.
        assert_eq!(pts.len(), lidar.beams * lidar.columns);
        for p in &pts {
            let w = pose * nalgebra::Point3::new(p[0] as f64, p[1] as f64, p[2] as f64);
            assert!(w.z > -0.1 && w.z < CEILING + 0.1, "{w:?}");
            assert!(
                w.x > -0.2 && w.x < 16.2 && w.y > -0.2 && w.y < 10.2,
                "{w:?}"
            );
        }
    }
}

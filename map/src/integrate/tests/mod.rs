//! The integrator's tests: against a reference update written the slow way, across walks,
//! kernels, thread counts and ray modes.

use super::marks::FrameMarks;
use super::ray::{CellKeys, RayMaker, Sides, RAY_CHUNK, SKIPPED};
#[cfg(target_arch = "x86_64")]
use super::update::{avx512::Avx512, observe_scalar};
use super::*;
use crate::coord::VoxelCoord;
use crate::kernel::Kernel;
#[cfg(target_arch = "x86_64")]
use crate::model::QuantizedModel;
use crate::model::{SensorModel, VoxelState};
use crate::raycast::for_each_voxel;
use crate::test_rng::Rng;
use hashbrown::HashMap;
use nalgebra::Isometry3;
use nalgebra::{Translation3, UnitQuaternion};

mod modes;
mod rays;
mod reference;
mod walks;

/// Integrate `pts` seen from the origin, exact mode, 2 threads.
fn at_origin(map: &mut OccupancyMap, max_range: f64, pts: &[[f32; 3]]) -> IntegrateReport {
    let frame = Frame {
        pose: Isometry3::identity(),
        points: pts,
    };
    integrator(2, max_range, RayMode::Exact)
        .integrate(map, &frame)
        .unwrap()
}

fn integrator(threads: usize, max_range: f64, mode: RayMode) -> Integrator {
    Integrator::new(IntegratorConfig {
        threads,
        max_range,
        mode,
        ..Default::default()
    })
    .unwrap()
}

/// Whether the CPU runs `kernel`; prints a notice when it does not, so that a skipped test
/// of a kernel is seen, not silently absent.
fn kernel_or_notice(kernel: Kernel, test: &str) -> bool {
    let yes = kernel.supported();
    if !yes {
        crate::kernel::skip_notice(format_args!(
            "{test}: the {} kernel is skipped, this CPU lacks its instructions",
            kernel.name()
        ));
    }
    yes
}

/// The kernels to test on this CPU (each other kernel skipped with a notice).
fn kernels(test: &str) -> Vec<Kernel> {
    Kernel::ALL
        .into_iter()
        .filter(|&k| kernel_or_notice(k, test))
        .collect()
}

fn snapshot(map: &OccupancyMap) -> Vec<(VoxelCoord, i8)> {
    map.assert_marks_in_step();
    let mut v: Vec<_> = map.grid().active_voxels().collect();
    v.sort();
    v
}

/// The update rule written the slow, obvious way: per ray a list of voxels, hit beats
/// free within a frame, then one update per voxel.
fn reference_integrate(map: &mut OccupancyMap, frame: &Frame<'_>, max_range: f64) {
    let tf = *map.transform();
    let o = tf.point_to_units(&Point3::from(frame.pose.translation.vector));
    let range = max_range / tf.resolution();
    let mut marks: HashMap<VoxelCoord, bool> = HashMap::new();
    for p in frame.points {
        if !p.iter().all(|c| c.is_finite()) {
            continue;
        }
        let w = frame.pose * Point3::new(p[0] as f64, p[1] as f64, p[2] as f64);
        let mut e = tf.point_to_units(&w);
        let d: Vec<f64> = (0..3).map(|a| e[a] - o[a]).collect();
        let len = d.iter().map(|c| c * c).sum::<f64>().sqrt();
        let hit = len <= range;
        if !hit {
            e = [0, 1, 2].map(|a| o[a] + d[a] * range / len);
        }
        let mut path = Vec::new();
        for_each_voxel(o, e, |v| path.push(v));
        let end = path.pop().unwrap();
        for v in path {
            marks.entry(v).or_insert(false);
        }
        if hit {
            marks.insert(end, true);
        }
    }
    let q = *map.quantized();
    for (v, hit) in marks {
        let old = map.value(v).unwrap_or(0);
        map.set_value(v, q.update(old, hit));
    }
}

fn random_frame(rng: &mut Rng, n: usize, radius: f64) -> (Isometry3<f64>, Vec<[f32; 3]>) {
    let pose = Isometry3::from_parts(
        Translation3::new(rng.f() * 4.0 - 2.0, rng.f() * 4.0 - 2.0, rng.f() - 0.5),
        UnitQuaternion::from_euler_angles(rng.f() * 6.0, rng.f() - 0.5, rng.f() * 6.0),
    );
    (pose, (0..n).map(|_| rng.ball(radius)).collect())
}

/// Sensor inside a closed box room: every wall voxel hit is occupied, the interior the
/// rays crossed is free, and nothing outside the walls is known.
#[test]
fn closed_box_room() {
    let (hx, hy, hz) = (2.0f64, 1.5f64, 1.2f64); // half extents, metres; walls at +-h
    let sensor = [0.33f64, -0.21, 0.1];
    let mut pts = Vec::new();
    let n = 200_000;
    for i in 0..n {
        // Fibonacci sphere directions.
        let z = 1.0 - 2.0 * (i as f64 + 0.5) / n as f64;
        let r = (1.0 - z * z).sqrt();
        let phi = i as f64 * 2.399963229728653;
        let d = [r * phi.cos(), r * phi.sin(), z];
        let t = (0..3)
            .map(|a| {
                let h = [hx, hy, hz][a];
                if d[a] > 0.0 {
                    (h - 0.01 - sensor[a]) / d[a]
                } else if d[a] < 0.0 {
                    (-h + 0.01 - sensor[a]) / d[a]
                } else {
                    f64::INFINITY
                }
            })
            .fold(f64::INFINITY, f64::min);
        pts.push([0, 1, 2].map(|a| (d[a] * t) as f32));
    }
    let pose = Isometry3::translation(sensor[0], sensor[1], sensor[2]);
    let mut map = OccupancyMap::new(0.05, SensorModel::default()).unwrap();
    let r = integrator(2, 10.0, RayMode::Exact)
        .integrate(&mut map, &Frame { pose, points: &pts })
        .unwrap();
    assert_eq!(r.cut_rays, 0);
    let tf = *map.transform();
    let state = |x: f64, y: f64, z: f64| map.state_at(&WorldPointT::new(x, y, z));
    // The wall voxel of every point is occupied.
    for p in pts.iter().step_by(97) {
        let w = pose * Point3::new(p[0] as f64, p[1] as f64, p[2] as f64);
        assert_eq!(map.state_at(&w), VoxelState::Occupied, "{w:?}");
    }
    // The interior, at least two voxels from the walls, is free wherever rays crossed it;
    // with 200k rays from one point that is every voxel (checked on a lattice).
    let res = tf.resolution();
    let mut checked = 0;
    let steps = |h: f64| (-((h - 2.0 * res) / 0.1) as i32)..=(((h - 2.0 * res) / 0.1) as i32);
    for ix in steps(hx) {
        for iy in steps(hy) {
            for iz in steps(hz) {
                let (x, y, z) = (
                    ix as f64 * 0.1 + 0.013,
                    iy as f64 * 0.1 + 0.013,
                    iz as f64 * 0.1 + 0.013,
                );
                assert_eq!(state(x, y, z), VoxelState::Free, "interior ({x}, {y}, {z})");
                checked += 1;
            }
        }
    }
    assert!(checked > 5000);
    // Outside the walls: unknown, and no known voxel lies beyond them.
    assert_eq!(state(hx + 0.3, 0.0, 0.0), VoxelState::Unknown);
    assert_eq!(state(0.0, -hy - 0.3, 0.0), VoxelState::Unknown);
    assert_eq!(state(0.0, 0.0, hz + 0.5), VoxelState::Unknown);
    for (v, _) in map.grid().active_voxels() {
        let c = tf.voxel_center(v);
        assert!(
            c.x.abs() < hx + res && c.y.abs() < hy + res && c.z.abs() < hz + res,
            "known outside: {c:?}"
        );
    }
    let counts = map.counts();
    assert!(
        counts.occupied > 1000 && counts.free > 100_000,
        "{counts:?}"
    );
}

type WorldPointT = crate::coord::WorldPoint;

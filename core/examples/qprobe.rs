// Throwaway probe (not committed): point query and first_hit timing.
use std::time::Instant;
use voxmap_core::io::pcd;
use voxmap_core::snapshot::{Meta, Plan, Scope, SnapshotView};
use voxmap_core::*;
fn main() {
    let name = std::env::args().nth(1).unwrap();
    let range: f64 = std::env::args().nth(2).unwrap().parse().unwrap();
    let reps: usize = std::env::args().nth(3).map_or(5, |s| s.parse().unwrap());
    let cloud = pcd::read(std::path::Path::new(&name)).unwrap();
    let mut map = OccupancyMap::new(0.1, SensorModel::default()).unwrap();
    let mut integ = Integrator::new(IntegratorConfig {
        threads: 2,
        max_range: range,
        mode: RayMode::Exact,
    })
    .unwrap();
    integ
        .integrate(
            &mut map,
            &Frame {
                pose: cloud.pose,
                points: &cloud.points,
            },
        )
        .unwrap();
    let bytes = Plan::new(&map, Scope::Whole, Meta::default()).to_vec();
    let view = SnapshotView::open(&bytes).unwrap();
    let n = map.grid().active_count() as usize;
    let stride = (n / 200_000).max(1);
    let mut pts: Vec<VoxelCoord> = map
        .grid()
        .active_voxels()
        .step_by(stride)
        .map(|(v, _)| v)
        .collect();
    let mut s = 0x2545F4914F6CDD1Du64;
    let mut rnd = || {
        s ^= s << 13;
        s ^= s >> 7;
        s ^= s << 17;
        s
    };
    for i in (1..pts.len()).rev() {
        let j = (rnd() % (i as u64 + 1)) as usize;
        pts.swap(i, j);
    }
    let mut segs = Vec::new();
    for _ in 0..20000 {
        let mut r = || (rnd() >> 11) as f64 / (1u64 << 53) as f64 * 2.0 - 1.0;
        let d = nalgebra::Vector3::new(r(), r(), r()).normalize() * 10.0;
        let a = WorldPoint::new(r() * 0.5, r() * 0.5, r() * 0.2);
        segs.push((a, a + d));
    }
    for _ in 0..reps {
        let t = Instant::now();
        let occ = pts
            .iter()
            .filter(|&&v| view.state(v) == VoxelState::Occupied)
            .count();
        let q = t.elapsed().as_secs_f64() * 1e9 / pts.len() as f64;
        let t = Instant::now();
        let hits = segs
            .iter()
            .filter(|(a, b)| matches!(view.first_hit(a, b, false), Ok(Some(_))))
            .count();
        let l = t.elapsed().as_secs_f64() * 1e9 / segs.len() as f64;
        println!("query {q:.1} ns  los {l:.0} ns  ({occ} {hits})");
    }
}

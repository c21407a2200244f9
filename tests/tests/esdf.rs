//! The distance field end to end: `replay --offline --esdf` and `voxmap distance` on the
//! real TUM frames against a brute-force nearest-obstacle search and against OctoMap's
//! dynamicEDT3D (Debian's libdynamicedt3d-dev, driven by bench/esdf_edt3d.cpp); a service
//! run with `--esdf` publishing the field in its snapshots.

use nalgebra::Isometry3;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};
use voxmap_client::{FramePublisher, MapControl, Nearest, SnapshotSubscriber, WorldPoint};
use voxmap_map::io::mapfile;
use voxmap_map::{OccupancyMap, VoxelCoord, VoxelState};
use voxmap_tests::{
    connect_with_retry, ok, room_scan, run_ok, tmpdir, unique_prefix, voxmap_bin, write_tum_frames,
    Service,
};

/// The TUM frames (every 2nd pixel) replayed offline into a map file, with the field kept
/// as the service keeps it; returns the map file.
fn tum_map(dir: &Path) -> PathBuf {
    let frames = write_tum_frames(dir, 2);
    let out = dir.join("tum.vxm");
    let log = ok(&[
        "replay",
        "--offline",
        "--esdf",
        "--out",
        out.to_str().unwrap(),
        "--poses",
        frames.join("poses.txt").to_str().unwrap(),
        "--max-range",
        "8",
        frames.to_str().unwrap(),
    ]);
    assert!(log.contains("distance field: 10 updates"), "{log}");
    out
}

/// Known voxels of the map, every `step`-th in leaf order, as their centres.
fn sample_known(map: &OccupancyMap, step: usize) -> Vec<(VoxelCoord, WorldPoint)> {
    let tf = map.transform();
    map.grid()
        .active_voxels()
        .step_by(step)
        .map(|(v, _)| (v, tf.voxel_center(v)))
        .collect()
}

/// `voxmap distance --voxel` at the points: the distance per point, `None` for -1 (none
/// within the max distance), NaN where the field does not reach.
fn voxmap_distances(
    file: &Path,
    points: &[WorldPoint],
    extra: &[&str],
    dir: &Path,
) -> Vec<Option<f64>> {
    let pts = dir.join("points.txt");
    let text: String = points
        .iter()
        .map(|p| format!("{} {} {}\n", p.x, p.y, p.z))
        .collect();
    std::fs::write(&pts, text).unwrap();
    let out = run_ok(
        Command::new(voxmap_bin())
            .args([
                "distance",
                file.to_str().unwrap(),
                "--voxel",
                "--points",
                pts.to_str().unwrap(),
            ])
            .args(extra),
    );
    let d: Vec<Option<f64>> = out
        .lines()
        .map(|l| {
            let d: f64 = l.split_whitespace().nth(3).unwrap().parse().unwrap();
            (d >= 0.0).then_some(d)
        })
        .collect();
    assert_eq!(d.len(), points.len());
    d
}

/// The nearest occupied voxel centre within `r` voxels, by scanning them all.
fn brute(map: &OccupancyMap, v: VoxelCoord, r: i32, unknown_is_obstacle: bool) -> Option<f64> {
    let mut best: Option<i32> = None;
    for dz in -r..=r {
        for dy in -r..=r {
            for dx in -r..=r {
                let d2 = dx * dx + dy * dy + dz * dz;
                if d2 >= r * r || best.is_some_and(|b| b <= d2) {
                    continue;
                }
                let s = map.state(v + VoxelCoord::new(dx, dy, dz));
                if s == VoxelState::Occupied || (unknown_is_obstacle && s == VoxelState::Unknown) {
                    best = Some(d2);
                }
            }
        }
    }
    best.map(|d2| f64::from(d2).sqrt() * map.resolution())
}

#[test]
fn tum_field_equals_a_brute_force_search_at_sampled_voxels() {
    let dir = tmpdir("esdf_brute");
    let file = tum_map(&dir);
    let map = mapfile::load_map(&file).unwrap();
    let sample = sample_known(&map, 97);
    assert!(sample.len() > 500, "{}", sample.len());
    let points: Vec<WorldPoint> = sample.iter().map(|s| s.1).collect();
    for (policy, unknown) in [("free", false), ("occupied", true)] {
        let got = voxmap_distances(
            &file,
            &points,
            &["--unknown", policy, "--max-distance", "1.0"],
            &dir,
        );
        let mut near = 0;
        for ((v, _), d) in sample.iter().zip(&got) {
            let want = brute(&map, *v, 10, unknown);
            match (d, want) {
                (Some(d), Some(w)) => {
                    assert!(
                        (d - w).abs() < 1e-5,
                        "{v:?} ({policy}): {d} vs brute force {w}"
                    );
                    near += 1;
                }
                (None, None) => {}
                _ => panic!("{v:?} ({policy}): {d:?} vs brute force {want:?}"),
            }
        }
        assert!(near > sample.len() / 4, "{near} of {}", sample.len());
    }
}

/// `bench/esdf_edt3d.cpp` built against Debian's dynamicEDT3D, or `None` (with a notice)
/// when the library is missing, unless VOXMAP_REQUIRE_EDT3D is set (as CI does).
fn edt3d() -> Option<PathBuf> {
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("../bench/esdf_edt3d.cpp");
    let bin = tmpdir("esdf_edt3d_bin").join("esdf_edt3d");
    let built = Command::new("g++")
        .args(["-O2", "-o", bin.to_str().unwrap(), src.to_str().unwrap()])
        .args(["-ldynamicedt3d", "-loctomap", "-loctomath"])
        .status()
        .is_ok_and(|s| s.success());
    if built {
        return Some(bin);
    }
    assert!(
        std::env::var_os("VOXMAP_REQUIRE_EDT3D").is_none(),
        "VOXMAP_REQUIRE_EDT3D is set but bench/esdf_edt3d.cpp does not build (apt-get install g++ libdynamicedt3d-dev liboctomap-dev)"
    );
    eprintln!("NOTICE: skipping the dynamicEDT3D comparison: g++ or libdynamicedt3d-dev missing");
    None
}

#[test]
fn tum_field_equals_dynamic_edt3d() {
    let Some(edt) = edt3d() else { return };
    let dir = tmpdir("esdf_edt3d");
    let file = tum_map(&dir);
    let bt = dir.join("tum.bt");
    ok(&[
        "export",
        file.to_str().unwrap(),
        "--bt",
        bt.to_str().unwrap(),
    ]);
    let map = mapfile::load_map(&file).unwrap();
    let (lo, hi) = {
        let b =
            map.grid()
                .active_voxels()
                .fold(([i32::MAX; 3], [i32::MIN; 3]), |(lo, hi), (v, _)| {
                    let a = v.to_array();
                    (
                        [0, 1, 2].map(|k| lo[k].min(a[k])),
                        [0, 1, 2].map(|k| hi[k].max(a[k])),
                    )
                });
        b
    };
    let sample = sample_known(&map, 31);
    let points: Vec<WorldPoint> = sample.iter().map(|s| s.1).collect();
    let pts = dir.join("q.txt");
    std::fs::write(
        &pts,
        points
            .iter()
            .map(|p| format!("{} {} {}\n", p.x, p.y, p.z))
            .collect::<String>(),
    )
    .unwrap();
    // Under `occupied` a shorter max distance, so that voxels far enough from the box's
    // faces (below) remain.
    for (policy, max) in [("free", 1.5), ("occupied", 0.5)] {
        let m = format!("{max}");
        let ours = voxmap_distances(
            &file,
            &points,
            &["--unknown", policy, "--max-distance", &m],
            &dir,
        );
        let theirs = run_ok(Command::new(&edt).args([
            "query",
            bt.to_str().unwrap(),
            &m,
            policy,
            pts.to_str().unwrap(),
        ]));
        let theirs: Vec<f64> = theirs
            .lines()
            .map(|l| l.split_whitespace().nth(3).unwrap().parse().unwrap())
            .collect();
        assert_eq!(theirs.len(), points.len());
        let (mut compared, mut near) = (0, 0);
        for (((v, p), d), t) in sample.iter().zip(&ours).zip(&theirs) {
            // dynamicEDT3D counts unknown voxels as obstacles only inside its box (the
            // map's bounds): compare away from the box's faces under `occupied`.
            let a = v.to_array();
            let margin = (max / map.resolution()).round() as i32;
            let inner = (0..3).all(|k| a[k] - lo[k] > margin && hi[k] - a[k] > margin);
            if policy == "occupied" && !inner {
                continue;
            }
            compared += 1;
            match d {
                Some(d) => {
                    assert!(
                        (d - t).abs() < 1e-4,
                        "{p:?} ({policy}): voxmap {d}, dynamicEDT3D {t}"
                    );
                    near += 1;
                }
                // None within the max distance: dynamicEDT3D answers at least its cap (a
                // voxel more).
                None => assert!(
                    *t >= max - 1e-4,
                    "{p:?} ({policy}): voxmap none, dynamicEDT3D {t}"
                ),
            }
        }
        assert!(
            compared > 200 && near > compared / 4,
            "{policy}: {near} near of {compared} compared"
        );
        eprintln!("{policy}: {compared} voxels compared with dynamicEDT3D, {near} within {max} m of an obstacle");
    }
}

#[test]
fn a_service_with_esdf_publishes_the_field_in_its_snapshots() {
    let prefix = unique_prefix("esdf");
    let _svc = Service::start(&prefix, &["--esdf", "--esdf-max-distance", "1.0"]);
    let mut sub = connect_with_retry(|| SnapshotSubscriber::connect(&prefix, "default"));
    let mut pubr = connect_with_retry(|| FramePublisher::connect(&prefix, "default"));
    let deadline = Instant::now() + Duration::from_secs(30);
    while sub.latest().unwrap().is_none() {
        sub.wait_for_update(Duration::from_millis(100)).unwrap();
        assert!(Instant::now() < deadline, "no initial snapshot");
    }
    // A room of half-extents 2 x 1.5 x 1.2 m around the sensor at the origin.
    let h = [2.0, 1.5, 1.2];
    pubr.publish(&Isometry3::identity(), 0, &room_scan(h, [0.0; 3], 40_000))
        .unwrap();
    loop {
        sub.wait_for_update(Duration::from_millis(100)).unwrap();
        if let Some(v) = sub.latest().unwrap() {
            if v.sequence() >= 1 {
                break;
            }
        }
        assert!(Instant::now() < deadline, "no snapshot of the scan");
    }
    let view = sub.latest().unwrap().unwrap();
    let f = view
        .distance_field()
        .expect("the snapshot carries the field");
    assert_eq!(f.max_distance(), 1.0);
    // 0.6 m in front of the +x wall (at 2.0 m): the wall is nearest, 0.6 m away.
    let p = WorldPoint::new(1.4, 0.0, 0.0);
    let d = f.distance_at(&p).expect("known");
    assert!((d - 0.6).abs() < 0.1, "{d}");
    let (_, g) = f.distance_and_gradient_at(&p).unwrap();
    assert!(g.x < -0.5, "the gradient points away from the wall: {g:?}");
    match f.nearest_obstacle(&p) {
        Nearest::At { centre, .. } => assert!((centre.x - 1.95).abs() < 0.06, "{centre:?}"),
        other => panic!("{other:?}"),
    }
    // The room's centre is more than 1 m from every wall: the max distance.
    assert_eq!(f.distance_at(&WorldPoint::new(0.0, 0.0, 0.0)), Some(1.0));
    assert_eq!(
        f.nearest_obstacle(&WorldPoint::new(0.0, 0.0, 0.0)),
        Nearest::NoneWithin
    );
    assert_eq!(
        f.distance_at(&WorldPoint::new(30.0, 0.0, 0.0)),
        None,
        "unknown space"
    );
    // Saved with the map, the field comes back with it: from the file, and in a service
    // that loads it (without building it again).
    let dir = tmpdir("esdf_save");
    let saved = dir.join("room.vxm");
    let control = connect_with_retry(|| MapControl::connect(&prefix, "default"));
    control.save(saved.to_str().unwrap()).unwrap();
    let info = ok(&["inspect", saved.to_str().unwrap()]);
    assert!(
        info.contains("version 2") && info.contains("distance field") && info.contains("to 1 m"),
        "{info}"
    );
    std::fs::write(dir.join("p.txt"), "1.4 0 0\n").unwrap();
    let line = ok(&[
        "distance",
        saved.to_str().unwrap(),
        "--max-distance",
        "1.0",
        "--points",
        dir.join("p.txt").to_str().unwrap(),
    ]);
    let from_file: f64 = line.split_whitespace().nth(3).unwrap().parse().unwrap();
    assert!((from_file - d).abs() < 1e-6, "{from_file} vs {d}");
    let prefix2 = unique_prefix("esdf_load");
    let svc2 = Service::start(
        &prefix2,
        &[
            "--esdf",
            "--esdf-max-distance",
            "1.0",
            "--load",
            saved.to_str().unwrap(),
        ],
    );
    let mut sub2 = connect_with_retry(|| SnapshotSubscriber::connect(&prefix2, "default"));
    let deadline = Instant::now() + Duration::from_secs(30);
    loop {
        sub2.wait_for_update(Duration::from_millis(100)).unwrap();
        if let Some(v) = sub2.latest().unwrap() {
            let f = v.distance_field().expect("the loaded field is published");
            assert_eq!(f.distance_at(&p), Some(d));
            break;
        }
        assert!(
            Instant::now() < deadline,
            "no snapshot from the loading service"
        );
    }
    drop(sub2);
    let (_, log) = svc2.signal_and_wait("TERM");
    assert!(log.contains("distance field read with the map"), "{log}");
}

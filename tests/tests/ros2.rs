//! `voxmap serve --ros2` against a ROS 2 peer voxmap did not write: Cyclone DDS's Python
//! binding with the ROS 2 types declared for it (`tests/ros/ros2_peer.py`), on loopback
//! with unicast discovery only (`ROS_STATIC_PEERS=127.0.0.1`), publishing the real TUM
//! frames as PointCloud2 in the camera's optical frame with the poses only in TF.

use std::collections::BTreeSet;
use std::path::Path;
use std::process::Command;
use voxmap_client::SnapshotView;
use voxmap_map::io::mapfile;
use voxmap_tests::{
    number_after, octomap_tool, ok, python_with, run_ok, tmpdir, unique_prefix, voxels, voxmap_bin,
    write_tum_frames,
};

const RES: f64 = 0.05;
const MAPPING: [&str; 8] = [
    "--resolution",
    "0.05",
    "--max-range",
    "8",
    "--threads",
    "2",
    "--mode",
    "exact",
];
const GRID_Z: (f64, f64) = (0.2, 1.5);

fn voxel_of(p: [f64; 3]) -> [i64; 3] {
    p.map(|c| (c / RES).floor() as i64)
}

/// Occupied voxels named by the centres of a float32 x y z buffer.
fn centres(bytes: &[u8]) -> BTreeSet<[i64; 3]> {
    assert_eq!(bytes.len() % 12, 0);
    bytes
        .chunks_exact(12)
        .map(|c| {
            let f = |i: usize| f32::from_le_bytes(c[i..i + 4].try_into().unwrap()) as f64;
            voxel_of([f(0), f(4), f(8)])
        })
        .collect()
}

/// The Python of the peer (Cyclone DDS and the scene's writer), or `None` with a notice;
/// CI sets VOXMAP_REQUIRE_ROS2, which makes its absence a failure.
fn python_with_cyclone() -> Option<std::path::PathBuf> {
    python_with(
        "rosbags, numpy, cyclonedds",
        "VOXMAP_REQUIRE_ROS2",
        "pip install rosbags numpy cyclonedds",
        "the live ROS 2 tests",
    )
}

fn json(path: &Path) -> serde_json::Value {
    serde_json::from_str(&std::fs::read_to_string(path).unwrap()).unwrap()
}

#[test]
fn a_cyclone_dds_peer_maps_through_the_bridge_and_reads_the_map_back() {
    let Some(py) = python_with_cyclone() else {
        return;
    };
    let dir = tmpdir("ros2");
    let frames = write_tum_frames(&dir, 4);
    let scripts = Path::new(env!("CARGO_MANIFEST_DIR")).join("ros");

    // The reference: the same scene as a bag (make_bags.py's writer), replayed offline
    // through the same TF matching.
    let bags = dir.join("bags");
    run_ok(Command::new(&py).arg(scripts.join("make_bags.py")).args([
        "tum",
        frames.to_str().unwrap(),
        bags.to_str().unwrap(),
    ]));
    let offline = dir.join("offline.map");
    let mut args = vec!["replay", "--offline", "--out", offline.to_str().unwrap()];
    args.extend(MAPPING);
    args.extend(["--topic", "/camera/depth/points"]);
    let bag = bags.join("lz4.mcap");
    args.push(bag.to_str().unwrap());
    ok(&args);
    let off_map = mapfile::load_map(&offline).unwrap();
    let off_bt = dir.join("offline.bt");
    ok(&[
        "export",
        offline.to_str().unwrap(),
        "--bt",
        off_bt.to_str().unwrap(),
    ]);
    let off_snapshot = mapfile::read_as_snapshot(&offline).unwrap();
    let off_view = SnapshotView::open(&off_snapshot).unwrap();
    let off_occupied: BTreeSet<[i64; 3]> = off_view
        .occupied_centers()
        .map(|p| voxel_of([p.x, p.y, p.z]))
        .collect();
    assert!(off_occupied.len() > 1000, "{}", off_occupied.len());

    // Rays for the raytrace service: from the first camera position towards a few occupied
    // voxels, and straight up; the answers must be the offline snapshot's.
    let poses = std::fs::read_to_string(frames.join("poses.txt")).unwrap();
    let w: Vec<f64> = poses
        .split_whitespace()
        .skip(1)
        .take(3)
        .map(|v| v.parse().unwrap())
        .collect();
    let origin = voxmap_map::WorldPoint::new(w[0], w[1], w[2]);
    let mut rays = Vec::new();
    for p in off_view.occupied_centers().step_by(997).take(4) {
        rays.push((
            [origin.x, origin.y, origin.z],
            [p.x - origin.x, p.y - origin.y, p.z - origin.z],
        ));
    }
    rays.push(([origin.x, origin.y, origin.z], [0.0, 0.0, 1.0]));
    let expected_rays: Vec<(bool, [f64; 3])> = rays
        .iter()
        .map(|(o, d)| {
            let n = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
            let to = voxmap_map::WorldPoint::new(
                o[0] + d[0] / n * 8.0,
                o[1] + d[1] / n * 8.0,
                o[2] + d[2] / n * 8.0,
            );
            match off_view.first_hit(&origin, &to, false).unwrap() {
                Some(v) => {
                    let c = off_view.transform().voxel_center(v);
                    (true, [c.x, c.y, c.z])
                }
                None => (false, [to.x, to.y, to.z]),
            }
        })
        .collect();
    assert!(expected_rays.iter().filter(|r| r.0).count() >= 3);

    // The service, with the bridge, on a domain of its own; the peers on the same one.
    let domain = (1 + std::process::id() % 100).to_string();
    let env = [
        ("ROS_DOMAIN_ID", domain.as_str()),
        ("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST"),
        ("ROS_STATIC_PEERS", "127.0.0.1"),
    ];
    let cfg = dir.join("ros2.toml");
    std::fs::write(
        &cfg,
        format!(
            "[ros2]\npublish_period_ms = 100.0\ntf_timeout_ms = 400.0\ngrid_z_min = {}\ngrid_z_max = {}\n",
            GRID_Z.0, GRID_Z.1
        ),
    )
    .unwrap();
    let prefix = unique_prefix("ros2");
    let ros2 = ["--ros2", "--config", cfg.to_str().unwrap()];
    let input = [
        "--ros2-cloud-topic",
        "/camera/depth/points",
        "--intake",
        "queue",
    ];
    let args = [&ros2[..], &input, &["--exit-after", "300"], &MAPPING].concat();
    let service = voxmap_tests::Service::spawn(&prefix, &args, &env);
    let out = dir.join("peer");
    std::fs::create_dir_all(&out).unwrap();
    let rays_json = serde_json::to_string(&rays).unwrap();
    let peer = |mode: &str| {
        let mut c = Command::new(&py);
        c.arg(scripts.join("ros2_peer.py")).arg(mode);
        if mode == "publish" {
            c.arg(&frames);
        }
        c.arg(&out).envs(env).env("VOXMAP_PEER_RAYS", &rays_json);
        c
    };
    let published = peer("publish").output().unwrap();
    let late = if published.status.success() {
        Some(peer("listen").output().unwrap())
    } else {
        None
    };
    let (status, log) = service.signal_and_wait("INT");
    assert!(
        published.status.success(),
        "peer: {}\n{}\nservice: {log}",
        String::from_utf8_lossy(&published.stdout),
        String::from_utf8_lossy(&published.stderr)
    );
    let late = late.unwrap();
    assert!(
        late.status.success(),
        "late peer: {}\nservice: {log}",
        String::from_utf8_lossy(&late.stderr)
    );
    assert!(status.success(), "{log}");
    let r = json(&out.join("publish.json"));
    let n = r["clouds"].as_u64().unwrap();
    assert_eq!(n, std::fs::read_dir(&frames).unwrap().count() as u64 - 1);

    // Every cloud integrated; the one with no transform and the malformed one counted.
    let exit = log
        .lines()
        .rfind(|l| l.contains("exiting; ros2:"))
        .unwrap_or_else(|| panic!("{log}"));
    assert_eq!(number_after(exit, "ros2:"), n + 2, "{exit}");
    assert_eq!(number_after(exit, "received,"), n, "{exit}");
    assert_eq!(number_after(exit, "integrated,"), 1, "{exit}");
    assert_eq!(number_after(exit, "transform,"), 1, "{exit}");

    // /voxmap/occupied: exactly the offline map's occupied voxels, in the map frame.
    let first = &r["first"];
    assert_eq!(first["occupied"]["frame"], "map");
    assert_eq!(first["occupied"]["point_step"], 12);
    let live = centres(&std::fs::read(out.join("first_occupied.bin")).unwrap());
    assert_eq!(live, off_occupied);

    // /voxmap/octomap_binary: OctoMap's binary data of the offline .bt, which OctoMap reads.
    let bt = std::fs::read(&off_bt).unwrap();
    let data = std::fs::read(out.join("first_octomap.bin")).unwrap();
    assert!(bt.ends_with(&data) && !data.is_empty());
    assert_eq!(
        (
            first["octomap"]["id"].as_str(),
            first["octomap"]["binary"].as_bool()
        ),
        (Some("OcTree"), Some(true))
    );
    assert_eq!(first["octomap"]["resolution"].as_f64(), Some(RES));
    let live_bt = dir.join("live.bt");
    let mut file = bt[..bt.len() - data.len()].to_vec();
    file.extend(&data);
    std::fs::write(&live_bt, &file).unwrap();
    let (off_ot, live_ot) = (dir.join("offline.ot"), dir.join("live.ot"));
    if octomap_tool(&[
        "convert_octree",
        off_bt.to_str().unwrap(),
        off_ot.to_str().unwrap(),
    ])
    .is_some()
    {
        octomap_tool(&[
            "convert_octree",
            live_bt.to_str().unwrap(),
            live_ot.to_str().unwrap(),
        ])
        .unwrap();
        let cmp = octomap_tool(&[
            "compare_octrees",
            off_ot.to_str().unwrap(),
            live_ot.to_str().unwrap(),
        ])
        .unwrap();
        let nodes = voxmap_map::io::octomap::read_bt(&bt).unwrap().nodes;
        assert_eq!(number_after(&cmp, "Done ("), nodes, "{cmp}");
    }

    // /voxmap/grid: occupied cells are the columns of occupied voxels centred in the z range.
    let (gw, gh) = (
        first["grid"]["width"].as_u64().unwrap(),
        first["grid"]["height"].as_u64().unwrap(),
    );
    let origin_xy = [
        first["grid"]["origin"][0].as_f64().unwrap(),
        first["grid"]["origin"][1].as_f64().unwrap(),
    ];
    let cells = std::fs::read(out.join("first_grid.bin")).unwrap();
    assert_eq!(cells.len() as u64, gw * gh);
    let grid_occupied: BTreeSet<[i64; 2]> = (0..cells.len())
        .filter(|&i| cells[i] == 100)
        .map(|i| {
            let (cx, cy) = ((i as u64 % gw) as f64, (i as u64 / gw) as f64);
            [
                ((origin_xy[0] + (cx + 0.5) * RES) / RES).floor() as i64,
                ((origin_xy[1] + (cy + 0.5) * RES) / RES).floor() as i64,
            ]
        })
        .collect();
    let columns: BTreeSet<[i64; 2]> = off_occupied
        .iter()
        .filter(|v| (GRID_Z.0..=GRID_Z.1).contains(&((v[2] as f64 + 0.5) * RES)))
        .map(|v| [v[0], v[1]])
        .collect();
    assert!(!columns.is_empty());
    assert_eq!(grid_occupied, columns);

    // The services, called from the peer.
    assert_eq!(r["save"][0], true, "{}", r["save"]);
    let saved = mapfile::load_map(&out.join("saved.map")).unwrap();
    assert_eq!(
        voxels(&saved),
        voxels(&off_map),
        "the live map is the offline map"
    );
    assert_eq!(r["save_bad"][0], false);
    assert!(
        r["save_bad"][1]
            .as_str()
            .unwrap()
            .contains("nonexistent-dir"),
        "{}",
        r["save_bad"]
    );
    let got_rays = r["rays"].as_array().unwrap();
    for (g, (hit, end)) in got_rays.iter().zip(&expected_rays) {
        assert_eq!(
            (g[0].as_bool(), g[1].as_bool()),
            (Some(true), Some(*hit)),
            "{g}"
        );
        for k in 0..3 {
            assert!(
                (g[2][k].as_f64().unwrap() - end[k]).abs() < 1e-9,
                "{g} vs {end:?}"
            );
        }
    }
    let bad_ray = got_rays.last().unwrap();
    assert_eq!(bad_ray[0], false, "a zero direction is refused: {bad_ray}");
    assert_eq!(r["reset"][0], true);
    assert_eq!(r["after_reset_occupied"], 0);
    assert_eq!(r["load"][0], true, "{}", r["load"]);
    assert_eq!(
        centres(&std::fs::read(out.join("loaded_occupied.bin")).unwrap()),
        off_occupied
    );

    // A peer that joined after everything still got the current map, latched.
    assert_eq!(
        centres(&std::fs::read(out.join("late_occupied.bin")).unwrap()),
        off_occupied
    );
    assert_eq!(std::fs::read(out.join("late_octomap.bin")).unwrap(), data);
    std::fs::remove_dir_all(&dir).unwrap();
}

/// Discovery variables ROS 2 would refuse are refused at start, naming the variable, and a
/// bad `[ros2]` setting likewise; nothing is left running.
#[test]
fn bad_discovery_variables_and_settings_stop_the_start_with_the_reason() {
    for (k, v) in [
        ("ROS_DOMAIN_ID", "300"),
        ("ROS_AUTOMATIC_DISCOVERY_RANGE", "everywhere"),
    ] {
        let out = Command::new(voxmap_bin())
            .args([
                "serve",
                "--prefix",
                &unique_prefix("ros2bad"),
                "--ros2",
                "--exit-after",
                "5",
            ])
            .env(k, v)
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success());
        assert!(err.contains(&format!("{k}='{v}'")), "{err}");
    }
    let out = Command::new(voxmap_bin())
        .args(["serve", "--prefix", &unique_prefix("ros2bad"), "--ros2"])
        .args(["--ros2-cloud-topic", "points@-3", "--exit-after", "5"])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert!(err.contains("points@-3"), "{err}");
}

/// `service_mapping = "cyclone"`: a request framed as rmw_cyclonedds_cpp frames it (the
/// client's GUID half and sequence number first) is answered with the same framing.
#[test]
fn services_answer_in_the_cyclone_rmw_mapping() {
    let Some(py) = python_with_cyclone() else {
        return;
    };
    let dir = tmpdir("ros2cyc");
    let cfg = dir.join("ros2.toml");
    std::fs::write(&cfg, "[ros2]\nservice_mapping = \"cyclone\"\n").unwrap();
    let domain = (101 + std::process::id() % 100).to_string();
    let env = [
        ("ROS_DOMAIN_ID", domain.as_str()),
        ("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST"),
        ("ROS_STATIC_PEERS", "127.0.0.1"),
    ];
    let prefix = unique_prefix("ros2cyc");
    let args = [
        "--ros2",
        "--config",
        cfg.to_str().unwrap(),
        "--exit-after",
        "120",
    ];
    let service = voxmap_tests::Service::spawn(&prefix, &args, &env);
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("ros/ros2_peer.py");
    let peer = Command::new(&py)
        .arg(script)
        .args(["cyclone-reset", dir.to_str().unwrap()])
        .envs(env)
        .output()
        .unwrap();
    let (_, log) = service.signal_and_wait("INT");
    assert!(
        peer.status.success(),
        "{}\n{log}",
        String::from_utf8_lossy(&peer.stderr)
    );
    let r = json(&dir.join("cyclone.json"));
    assert_eq!(r["success"], true, "{r}");
    assert_eq!(r["guid"], serde_json::json!([1, 2, 3, 4, 5, 6, 7, 8]));
    assert_eq!(r["sequence"], serde_json::json!([0, 77]));
    std::fs::remove_dir_all(&dir).unwrap();
}

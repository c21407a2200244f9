//! ROS 2 bags into `voxmap replay` and `voxmap inspect`, written by independent writers
//! (`tests/ros/make_bags.py`: the Python `rosbags` library and Foxglove's `mcap` writer),
//! never by voxmap's own code.

use std::path::{Path, PathBuf};
use std::process::Command;
use voxmap_map::io::mapfile;
use voxmap_tests::{
    ok, python_with_rosbags, tmpdir, unique_prefix, voxels, voxmap, write_tum_frames, Service,
};

fn make_bags(py: &Path, args: &[&str]) {
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("ros/make_bags.py");
    let out = Command::new(py)
        .arg(&script)
        .args(args)
        .output()
        .expect("run python");
    assert!(
        out.status.success(),
        "make_bags.py {args:?}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
}

const MAPPING: [&str; 6] = ["--resolution", "0.05", "--max-range", "8", "--threads", "2"];

fn replay_offline(input: &Path, out: &Path, extra: &[&str]) -> String {
    let mut args = vec!["replay", "--offline", "--out", out.to_str().unwrap()];
    args.extend(MAPPING);
    args.extend(extra);
    args.push(input.to_str().unwrap());
    ok(&args)
}

fn find_ext(dir: &Path, ext: &str) -> PathBuf {
    std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .find(|p| p.extension().is_some_and(|e| e == ext))
        .unwrap_or_else(|| panic!("no .{ext} in {}", dir.display()))
}

/// The TUM frames' poses split into a TF tree (static map -> odom, dynamic odom ->
/// base_link sampled 10 ms either side of each cloud, static base_link -> camera_link ->
/// optical frame), the clouds in six layouts (PCL XYZRGB, organized with NaN and inf,
/// float64 in another field order, big-endian, row padding, Ouster's): the bag's map is
/// the map of the same points with their poses given directly, voxel for voxel, from
/// sqlite3, MCAP with zstd chunks, MCAP with lz4 chunks, and with the moving link taken
/// from an Odometry topic instead of /tf.
#[test]
fn bags_in_every_storage_make_the_map_of_the_frames_posed_directly() {
    let Some(py) = python_with_rosbags() else {
        return;
    };
    let dir = tmpdir("bags_tum");
    let frames_dir = write_tum_frames(&dir, 2);
    let bags = dir.join("bags");
    make_bags(
        &py,
        &["tum", frames_dir.to_str().unwrap(), bags.to_str().unwrap()],
    );

    let reference = dir.join("direct.vxm");
    let out = replay_offline(
        &frames_dir,
        &reference,
        &["--poses", frames_dir.join("poses.txt").to_str().unwrap()],
    );
    assert!(out.contains("replayed 10 frames"), "{out}");
    let want = voxels(&mapfile::load_map(&reference).unwrap());
    assert!(want.len() > 100_000, "{}", want.len());

    let db3 = find_ext(&bags.join("sqlite"), "db3");
    let cases: [(&str, PathBuf, &[&str]); 5] = [
        ("sqlite3 directory", bags.join("sqlite"), &[]),
        ("sqlite3 .db3 file", db3, &[]),
        ("MCAP zstd directory", bags.join("mcap_zstd"), &[]),
        ("MCAP lz4 file", bags.join("lz4.mcap"), &[]),
        (
            "MCAP zstd, poses from /odom",
            bags.join("mcap_zstd"),
            &["--pose-topic", "/odom"],
        ),
    ];
    for (what, bag, extra) in cases {
        let map = dir.join("bag.vxm");
        let out = replay_offline(&bag, &map, extra);
        assert!(out.contains("replayed 10 frames"), "{what}: {out}");
        // The organized layouts carry NaN and infinite points: skipped and counted.
        assert!(out.contains("non-finite points skipped"), "{what}: {out}");
        assert!(!out.contains("skipped ("), "{what}: {out}");
        let got = voxels(&mapfile::load_map(&map).unwrap());
        if got != want {
            let (g, w): (std::collections::BTreeSet<_>, std::collections::BTreeSet<_>) =
                (got.iter().collect(), want.iter().collect());
            let extra: Vec<_> = g.difference(&w).take(5).collect();
            let missing: Vec<_> = w.difference(&g).take(5).collect();
            panic!(
                "{what}: {} voxels against {}; {} not in the direct map (first {extra:?}), {} missing (first {missing:?})",
                got.len(),
                want.len(),
                g.difference(&w).count(),
                w.difference(&g).count()
            );
        }
    }

    // To a running service, like every other input.
    let prefix = unique_prefix("bag_svc");
    let svc = Service::start(&prefix, &MAPPING[..4]);
    let online = dir.join("online.vxm");
    let out = ok(&[
        "replay",
        "--prefix",
        &prefix,
        "--save",
        online.to_str().unwrap(),
        bags.join("lz4.mcap").to_str().unwrap(),
    ]);
    assert!(
        out.contains("10 frames integrated, 0 dropped, 0 rejected"),
        "{out}"
    );
    drop(svc);
    assert!(
        voxels(&mapfile::load_map(&online).unwrap()) == want,
        "the service's map differs"
    );

    // inspect: topics with types and counts, the span, the TF tree.
    let text = ok(&["inspect", bags.join("mcap_zstd").to_str().unwrap()]);
    for needle in [
        "/camera/depth/points",
        "sensor_msgs/msg/PointCloud2",
        "tf2_msgs/msg/TFMessage",
        "nav_msgs/msg/Odometry",
        "map -> odom  static",
        "base_link -> camera_link  static",
        "camera_link -> camera_rgb_optical_frame  static",
        "odom -> base_link  dynamic, 20 samples",
        "time span",
    ] {
        assert!(text.contains(needle), "'{needle}' not in:\n{text}");
    }
    let clouds = text
        .lines()
        .find(|l| l.contains("/camera/depth/points"))
        .unwrap();
    assert!(clouds.trim_end().ends_with("10 messages"), "{clouds}");
    std::fs::remove_dir_all(&dir).unwrap();
}

/// Each kind of bad cloud and transform is skipped with its reason and counted, or with
/// `--on-error abort` stops the replay naming the topic, the index and the reason.
#[test]
fn bad_clouds_and_transforms_are_skipped_and_counted_by_reason() {
    let Some(py) = python_with_rosbags() else {
        return;
    };
    let dir = tmpdir("bags_bad");
    make_bags(&py, &["bad", dir.to_str().unwrap()]);
    let bag = dir.join("bad");
    let map = dir.join("m.vxm");
    let out = replay_offline(&bag, &map, &["--on-error", "skip"]);
    for needle in [
        "replayed 3 frames",
        "120 non-finite points skipped",
        "7 skipped (",
        "1 no x, y or z field",
        "1 data size disagrees",
        "1 coordinate not float32/float64",
        "1 no transform (unknown frame)",
        "1 no transform (extrapolation into the future)",
        "1 no transform (extrapolation into the past)",
        "1 row_step shorter than a row",
        "2 transforms ignored",
    ] {
        assert!(out.contains(needle), "'{needle}' not in:\n{out}");
    }
    assert!(mapfile::load_map(&map).unwrap().counts().occupied > 0);

    let args = [
        "replay",
        "--offline",
        "--out",
        map.to_str().unwrap(),
        bag.to_str().unwrap(),
    ];
    let r = voxmap(&args);
    let err = String::from_utf8_lossy(&r.stderr);
    assert!(!r.status.success());
    assert!(
        err.contains("/lidar/points cloud 1: the cloud has no 'z' field"),
        "{err}"
    );

    // A message on the cloud topic that is not a PointCloud2.
    let r = voxmap(&[
        "replay",
        "--offline",
        "--out",
        map.to_str().unwrap(),
        "--on-error",
        "skip",
        dir.join("garbage.mcap").to_str().unwrap(),
    ]);
    let out = String::from_utf8_lossy(&r.stdout);
    assert!(r.status.success(), "{}", String::from_utf8_lossy(&r.stderr));
    assert!(out.contains("1 skipped (1 not a PointCloud2)"), "{out}");

    // Topic choice: with two cloud topics and no --topic, the error lists both.
    let two = dir.join("two_topics.mcap");
    let r = voxmap(&[
        "replay",
        "--offline",
        "--out",
        map.to_str().unwrap(),
        two.to_str().unwrap(),
    ]);
    let err = String::from_utf8_lossy(&r.stderr);
    assert!(
        err.contains("2 PointCloud2 topics; choose with --topic: /front/points, /rear/points"),
        "{err}"
    );
    let out = ok(&[
        "replay",
        "--offline",
        "--out",
        map.to_str().unwrap(),
        "--topic",
        "/rear/points",
        "--map-frame",
        "lidar",
        two.to_str().unwrap(),
    ]);
    assert!(out.contains("replayed 1 frames"), "{out}");
    // Topic choice: a topic that is not there is named with the ones that are.
    let r = voxmap(&[
        "replay",
        "--offline",
        "--out",
        map.to_str().unwrap(),
        "--topic",
        "/nope",
        bag.to_str().unwrap(),
    ]);
    let err = String::from_utf8_lossy(&r.stderr);
    assert!(
        err.contains("no PointCloud2 topic '/nope' (PointCloud2 topics: /lidar/points)"),
        "{err}"
    );
    std::fs::remove_dir_all(&dir).unwrap();
}

/// A bag file cut off in the middle of a chunk: the clouds before the damage are mapped,
/// the error names the file and the offset, nothing panics.
#[test]
fn a_bag_truncated_mid_chunk_keeps_the_clouds_before_the_damage() {
    let Some(py) = python_with_rosbags() else {
        return;
    };
    let dir = tmpdir("bags_cut");
    let frames_dir = write_tum_frames(&dir, 4);
    make_bags(
        &py,
        &[
            "tum",
            frames_dir.to_str().unwrap(),
            dir.join("bags").to_str().unwrap(),
        ],
    );
    let whole = std::fs::read(dir.join("bags/lz4.mcap")).unwrap();
    let cut = dir.join("cut.mcap");
    // 60% of the way in: inside a chunk (chunks are 256 KiB, a cloud 0.25-0.8 MB).
    let at = whole.len() * 6 / 10;
    std::fs::write(&cut, &whole[..at]).unwrap();

    let map = dir.join("m.vxm");
    let out = replay_offline(&cut, &map, &["--on-error", "skip"]);
    let n: u32 = out
        .split("replayed ")
        .nth(1)
        .and_then(|s| s.split(' ').next())
        .and_then(|s| s.parse().ok())
        .unwrap_or_else(|| panic!("{out}"));
    assert!(
        (3..10).contains(&n),
        "{n} frames of 10 before the cut at 60%: {out}"
    );
    assert!(out.contains("1 damaged bag file"), "{out}");
    assert!(mapfile::load_map(&map).unwrap().counts().occupied > 1000);

    let r = voxmap(&[
        "replay",
        "--offline",
        "--out",
        map.to_str().unwrap(),
        cut.to_str().unwrap(),
    ]);
    let err = String::from_utf8_lossy(&r.stderr);
    assert_eq!(r.status.code(), Some(1), "{err}");
    assert!(
        err.contains(&format!("cut.mcap: MCAP damaged at byte {at} of {at}")),
        "{err}"
    );
    assert!(!err.contains("panicked"), "{err}");
    std::fs::remove_dir_all(&dir).unwrap();
}

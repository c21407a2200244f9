//! The tile store through the tools: `replay --offline` under a memory budget gives the
//! unbudgeted map; `export` and `inspect` read a store; and crash trials: a replay that
//! evicts after every frame and saves every few frames, killed with SIGKILL at random
//! moments, leaves a store that opens, checks whole, and holds exactly the map of the
//! frames its last save covered, never less than the last save it reported.

use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
use std::io::Read;
use std::path::Path;
use std::process::{Command, Stdio};
use std::time::Duration;
use voxmap_map::io::pcd;
use voxmap_map::{Frame, FrameStamp, IntegratorConfig, Mapper, MapperConfig};
use voxmap_tests::{ok, tmpdir, voxmap, voxmap_bin, TestRng};

const FRAMES: usize = 40;
const SAVE_EVERY: usize = 4;
const MAPPING: [&str; 6] = ["--resolution", "0.1", "--max-range", "7", "--threads", "2"];

/// A sensor moving 1.6 m a frame down a corridor with pillars: it leaves each tile
/// (12.8 m) behind within a few frames.
fn frames() -> Vec<(Isometry3<f64>, Vec<[f32; 3]>)> {
    let mut rng = TestRng(3);
    (0..FRAMES)
        .map(|i| {
            let x = 1.6 * i as f64;
            let pose = Isometry3::from_parts(
                Translation3::new(x, 0.3 * (i % 2) as f64, 1.2),
                UnitQuaternion::from_axis_angle(&Vector3::z_axis(), 0.1 * i as f64),
            );
            let pts = (0..6000)
                .map(|_| {
                    // World points on the corridor's walls (y = +-3), floor and pillars.
                    let w = match rng.below(3) {
                        0 => [
                            x + 12.0 * rng.f() - 6.0,
                            if rng.f() < 0.5 { -3.0 } else { 3.0 },
                            3.0 * rng.f(),
                        ],
                        1 => [x + 12.0 * rng.f() - 6.0, 6.0 * rng.f() - 3.0, 0.0],
                        _ => {
                            let px = (x / 4.0).round() * 4.0 + 0.2 * rng.f();
                            [px, 1.5 + 0.2 * rng.f(), 3.0 * rng.f()]
                        }
                    };
                    let v = pose.inverse_transform_point(&w.into());
                    [v.x as f32, v.y as f32, v.z as f32]
                })
                .collect();
            (pose, pts)
        })
        .collect()
}

fn write_frames(dir: &Path) -> Vec<(Isometry3<f64>, Vec<[f32; 3]>)> {
    std::fs::create_dir_all(dir).unwrap();
    let f = frames();
    for (i, (pose, points)) in f.iter().enumerate() {
        let cloud = pcd::PointCloud {
            points: points.clone(),
            pose: *pose,
        };
        pcd::write(&dir.join(format!("frame_{i:03}.pcd")), &cloud).unwrap();
    }
    f
}

/// The map file of the first `n` frames, mapped without a store, as bytes.
fn reference(frames: &[(Isometry3<f64>, Vec<[f32; 3]>)], n: usize, dir: &Path) -> Vec<u8> {
    let mut m = Mapper::new(&MapperConfig {
        resolution: 0.1,
        integrator: IntegratorConfig {
            threads: 2,
            max_range: 7.0,
            pin_threads: false,
            ..Default::default()
        },
        ..Default::default()
    })
    .unwrap();
    for (i, (pose, pts)) in frames[..n].iter().enumerate() {
        let frame = Frame {
            pose: *pose,
            points: pts,
        };
        m.insert(
            &frame,
            FrameStamp {
                sequence: i as u64 + 1,
                stamp_ns: 0,
            },
        )
        .unwrap();
    }
    let p = dir.join(format!("ref-{n}.vxm"));
    m.write_map_file(&p).unwrap();
    std::fs::read(p).unwrap()
}

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

#[test]
fn replay_under_a_budget_equals_replay_without_and_the_store_exports_it() {
    let dir = tmpdir("store_replay");
    let scans = dir.join("scans");
    let f = write_frames(&scans);
    let free = dir.join("free.vxm");
    ok(&[
        &["replay", "--offline", "--out", s(&free)],
        &MAPPING[..],
        &[s(&scans)],
    ]
    .concat());
    let store = dir.join("store");
    let budgeted = dir.join("budget.vxm");
    let out = ok(&[
        &[
            "replay",
            "--offline",
            "--out",
            s(&budgeted),
            "--store",
            s(&store),
            "--memory-budget",
            "2M",
        ],
        &MAPPING[..],
        &[s(&scans)],
    ]
    .concat());
    assert!(out.contains("evicted") && out.contains("peak RSS"), "{out}");
    let want = std::fs::read(&free).unwrap();
    assert_eq!(std::fs::read(&budgeted).unwrap(), want, "{out}");
    assert_eq!(reference(&f, FRAMES, &dir), want);
    let exported = dir.join("export.vxm");
    ok(&["export", s(&store), "--out", s(&exported)]);
    assert_eq!(std::fs::read(&exported).unwrap(), want);
    let inspect = ok(&["inspect", s(&store), "--check"]);
    assert!(
        inspect.contains("0 refused") && inspect.contains("generation"),
        "{inspect}"
    );

    // With the distance field: the same map file, field and all.
    let esdf = ["--esdf", "--esdf-max-distance", "1.0"];
    let free_field = dir.join("free-field.vxm");
    ok(&[
        &["replay", "--offline", "--out", s(&free_field)],
        &MAPPING[..],
        &esdf[..],
        &[s(&scans)],
    ]
    .concat());
    let field_store = dir.join("field-store");
    let budgeted_field = dir.join("budget-field.vxm");
    let out = ok(&[
        &["replay", "--offline", "--out", s(&budgeted_field)],
        &["--store", s(&field_store), "--memory-budget", "3M"],
        &MAPPING[..],
        &esdf[..],
        &[s(&scans)],
    ]
    .concat());
    assert!(out.contains("evicted"), "{out}");
    let want_field = std::fs::read(&free_field).unwrap();
    assert!(want_field.len() > want.len() + 10_000);
    assert!(
        std::fs::read(&budgeted_field).unwrap() == want_field,
        "{out}"
    );

    // Bad settings are refused with a clear error.
    for (args, why) in [
        (vec!["--memory-budget", "64M"], "needs a store"),
        (
            vec!["--memory-budget", "lots", "--store", s(&store)],
            "suffix must be",
        ),
        (
            vec!["--memory-budget", "x12M", "--store", s(&store)],
            "not a whole number",
        ),
    ] {
        let o = voxmap(
            &[
                &["replay", "--offline", "--out", s(&budgeted)],
                &args[..],
                &[s(&scans)],
            ]
            .concat(),
        );
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(!o.status.success() && err.contains(why), "{args:?}: {err}");
    }
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_store_killed_at_any_moment_holds_its_last_save_exactly() {
    let dir = tmpdir("store_crash");
    let scans = dir.join("scans");
    let f = write_frames(&scans);
    let refs: Vec<Vec<u8>> = (0..=FRAMES / SAVE_EVERY)
        .map(|k| reference(&f, k * SAVE_EVERY, &dir))
        .collect();
    let replay = |store: &Path| {
        Command::new(voxmap_bin())
            .args([
                "replay",
                "--offline",
                "--out",
                s(&dir.join("unused.vxm")),
                "--store",
                s(store),
            ])
            .args([
                "--memory-budget",
                "1M",
                "--save-every",
                &SAVE_EVERY.to_string(),
            ])
            .args(MAPPING)
            .arg(s(&scans))
            .stdout(Stdio::piped())
            .stderr(Stdio::null())
            .spawn()
            .unwrap()
    };
    // One run to its end: the store of all frames.
    let whole = dir.join("store-whole");
    assert!(replay(&whole).wait().unwrap().success());
    assert_eq!(
        voxmap_map::store::read_manifest(&whole)
            .unwrap()
            .last_frame
            .0 as usize,
        FRAMES
    );
    let mut rng = TestRng(99);
    let (mut mid_run, trials) = (0, 24);
    for trial in 0..trials {
        let store = dir.join(format!("store-{trial}"));
        let mut child = replay(&store);
        // Killed a random few milliseconds after a random save (or at start-up): in the
        // evictions of the frames after it, or in the next save.
        let after = rng.below((FRAMES / SAVE_EVERY) as u64) as usize * SAVE_EVERY;
        let mut out = std::io::BufReader::new(child.stdout.take().unwrap());
        let mut said = String::new();
        if after > 0 {
            let mark = format!("store saved: frame {after},");
            let mut line = String::new();
            while std::io::BufRead::read_line(&mut out, &mut line).unwrap() > 0 {
                said.push_str(&line);
                if line.starts_with(&mark) {
                    break;
                }
                line.clear();
            }
        }
        std::thread::sleep(Duration::from_micros(rng.below(8000)));
        let _ = child.kill(); // SIGKILL
        let status = child.wait().unwrap();
        out.read_to_string(&mut said).unwrap();
        // The last save the replay reported before it died.
        let acknowledged = said
            .lines()
            .filter_map(|l| {
                l.strip_prefix("store saved: frame ")?
                    .split(',')
                    .next()?
                    .parse::<usize>()
                    .ok()
            })
            .max()
            .unwrap_or(0);
        if !status.success() {
            mid_run += 1;
        }
        if !voxmap_map::store::exists(&store) {
            assert_eq!(
                acknowledged, 0,
                "trial {trial}: no store, yet a save was reported"
            );
            continue;
        }
        let manifest = voxmap_map::store::read_manifest(&store)
            .unwrap_or_else(|e| panic!("trial {trial}: the store does not open: {e}"));
        let saved = manifest.last_frame.0 as usize;
        assert!(
            saved >= acknowledged,
            "trial {trial}: saved frame {saved} < acknowledged {acknowledged}"
        );
        assert!(
            saved.is_multiple_of(SAVE_EVERY),
            "trial {trial}: frame {saved}"
        );
        let inspect = ok(&["inspect", s(&store), "--check"]);
        assert!(inspect.contains(" 0 refused"), "trial {trial}: {inspect}");
        let out = dir.join(format!("export-{trial}.vxm"));
        ok(&["export", s(&store), "--out", s(&out)]);
        assert!(
            std::fs::read(&out).unwrap() == refs[saved / SAVE_EVERY],
            "trial {trial}: the store's map is not the map of its first {saved} frames"
        );
        // And it goes on: a replay resumes the store where it stopped.
        let _ = std::fs::remove_dir_all(&store);
    }
    eprintln!("{mid_run} of {trials} kills landed mid-run");
    assert!(
        mid_run >= trials * 2 / 3,
        "only {mid_run} of {trials} kills landed mid-run"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

/// Wait until the service has integrated `n` frames.
fn wait_integrated(ctl: &voxmap_client::MapControl, n: u64) {
    let deadline = std::time::Instant::now() + Duration::from_secs(60);
    while ctl.stats().unwrap().frames_integrated < n {
        assert!(
            std::time::Instant::now() < deadline,
            "frames not integrated"
        );
        std::thread::sleep(Duration::from_millis(20));
    }
}

#[test]
fn a_service_keeps_its_map_and_field_in_a_store_saves_it_and_loads_another_lazily() {
    use voxmap_client::{FramePublisher, MapControl, MapScope};
    use voxmap_tests::{connect_with_retry, unique_prefix, Service};
    let dir = tmpdir("store_serve");
    let scans = dir.join("scans");
    let f = write_frames(&scans);
    let esdf = ["--esdf", "--esdf-max-distance", "1.0"];
    // Another store of the same map parameters and field, built offline.
    let other = dir.join("other");
    ok(&[
        &["replay", "--offline", "--out", s(&dir.join("other.vxm"))][..],
        &["--store", s(&other)],
        &MAPPING[..],
        &esdf[..],
        &[s(&scans)],
    ]
    .concat());
    let other_tiles = ok(&["inspect", s(&other)]);
    assert!(other_tiles.contains("distance field"), "{other_tiles}");

    let store = dir.join("store");
    let prefix = unique_prefix("store-serve");
    let serve = [
        &["--store", s(&store), "--memory-budget", "4M"][..],
        &["--store-save-interval", "1"],
        &MAPPING[..4],
        &esdf[..],
    ]
    .concat();
    let svc = Service::start(&prefix, &serve);
    let ctl = connect_with_retry(|| MapControl::connect(&prefix, "default"));
    let mut frames_out = connect_with_retry(|| FramePublisher::connect(&prefix, "default"));
    // Frames are published once the service listens: its first stats answer says so.
    ctl.stats().unwrap();
    for (i, (pose, pts)) in f.iter().take(24).enumerate() {
        frames_out
            .publish(pose, i as u64 * 100_000_000, pts)
            .unwrap();
        wait_integrated(&ctl, i as u64 + 1);
    }
    let st = ctl.stats().unwrap();
    assert!(
        st.tile_evictions > 0 && st.tiles_stored > 0 && st.memory_budget_bytes == 4 << 20,
        "{st:?}"
    );
    // The periodic save commits without a request.
    let deadline = std::time::Instant::now() + Duration::from_secs(20);
    let generation = || {
        let text = ok(&["inspect", s(&store)]);
        text.lines()
            .find_map(|l| l.trim().strip_prefix("generation"))
            .and_then(|v| v.trim().parse::<u64>().ok())
            .unwrap_or(0)
    };
    while generation() == 0 {
        assert!(std::time::Instant::now() < deadline, "no periodic save");
        std::thread::sleep(Duration::from_millis(200));
    }
    ctl.save(s(&store)).unwrap();
    let committed = ok(&["inspect", s(&store), "--check"]);
    assert!(committed.contains("0 refused"), "{committed}");

    // Loading another store continues it lazily: nothing is in memory until reached.
    ctl.load(s(&other)).unwrap();
    let st = ctl.stats().unwrap();
    assert_eq!((st.map_leaves, st.tiles_resident), (0, 0), "{st:?}");
    assert!(st.tiles_stored > 0);
    // A snapshot window around the sensor brings its tiles back.
    ctl.set_scope(MapScope::AroundSensor {
        half_extents: [4.0, 4.0, 2.0],
    })
    .unwrap();
    let deadline = std::time::Instant::now() + Duration::from_secs(20);
    while ctl.stats().unwrap().tile_loads == 0 {
        assert!(std::time::Instant::now() < deadline, "no tile loaded");
        std::thread::sleep(Duration::from_millis(50));
    }
    // A store of another resolution is refused; the service keeps the one it has.
    let coarse = dir.join("coarse");
    ok(&[
        &["replay", "--offline", "--out", s(&dir.join("coarse.vxm"))][..],
        &["--store", s(&coarse), "--resolution", "0.2"],
        &[s(&scans)],
    ]
    .concat());
    let before = ctl.stats().unwrap().tiles_stored;
    let e = ctl.load(s(&coarse)).unwrap_err().to_string();
    assert!(e.contains("resolution"), "{e}");
    assert_eq!(ctl.stats().unwrap().tiles_stored, before);

    // Back to the first store; SIGTERM saves it; a restart with --load continues it.
    ctl.load(s(&store)).unwrap();
    let (status, log) = svc.signal_and_wait("TERM");
    assert!(status.success(), "{log}");
    assert!(log.contains("tile store saved"), "{log}");
    let svc = Service::start(
        &prefix,
        &[&["--load", s(&store)][..], &MAPPING[..4], &esdf[..]].concat(),
    );
    let ctl = connect_with_retry(|| MapControl::connect(&prefix, "default"));
    let st = ctl.stats().unwrap();
    assert!(st.tiles_stored > 0 && st.map_leaves == 0, "{st:?}");
    drop(svc);
    let _ = std::fs::remove_dir_all(&dir);
}

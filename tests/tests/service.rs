//! Cross-process tests: the real `voxmap serve` binary, real iceoryx2 shared memory.

use nalgebra::Isometry3;
use std::time::{Duration, Instant};
use voxmap_client::{FramePublisher, SnapshotSubscriber, VoxelState, WorldPoint};
use voxmap_tests::{connect_with_retry, room_scan, unique_prefix, Service};

const H: [f64; 3] = [2.0, 1.5, 1.2];
const SENSOR: [f64; 3] = [0.3, -0.2, 0.1];

/// Wait until the planner holds a snapshot with `sequence >= seq` and `known > 0`.
fn wait_for_seq(sub: &mut SnapshotSubscriber, seq: u64, min_known: u64) -> bool {
    let deadline = Instant::now() + Duration::from_secs(30);
    while Instant::now() < deadline {
        sub.wait_for_update(Duration::from_millis(200)).unwrap();
        if let Some(v) = sub.latest().unwrap() {
            if v.sequence() >= seq && v.counts().0 >= min_known {
                return true;
            }
        }
    }
    false
}

/// A service with one 20k-point room scan integrated and published.
struct Scanned {
    svc: Service,
    sub: SnapshotSubscriber,
    pubr: FramePublisher,
    pose: Isometry3<f64>,
    /// Known voxels in the snapshot of the scan.
    known: u64,
}

fn start_and_scan(prefix: &str, extra: &[&str]) -> Scanned {
    let svc = Service::start(prefix, extra);
    let mut sub = connect_with_retry(|| SnapshotSubscriber::connect(prefix, "default"));
    let mut pubr = connect_with_retry(|| FramePublisher::connect(prefix, "default"));
    // The service subscribes to frames before it publishes its first (empty) snapshot:
    // frames sent before that would be lost.
    assert!(
        wait_for_seq(&mut sub, 0, 0),
        "service never published its initial snapshot"
    );
    let pose = Isometry3::translation(SENSOR[0], SENSOR[1], SENSOR[2]);
    pubr.publish(&pose, 0, &room_scan(H, SENSOR, 20_000))
        .unwrap();
    assert!(wait_for_seq(&mut sub, 0, 1000), "no snapshot of the scan");
    let known = sub.latest().unwrap().unwrap().counts().0;
    Scanned {
        svc,
        sub,
        pubr,
        pose,
        known,
    }
}

#[test]
fn closed_room_scan_becomes_a_snapshot_read_in_place() {
    let prefix = unique_prefix("room");
    let svc = Service::start(&prefix, &["--resolution", "0.05"]);
    let mut sub = connect_with_retry(|| SnapshotSubscriber::connect(&prefix, "default"));
    let mut pubr = connect_with_retry(|| FramePublisher::connect(&prefix, "default"));
    // The service publishes an empty snapshot at start.
    assert!(wait_for_seq(&mut sub, 0, 0), "no initial snapshot");

    let pose = Isometry3::translation(SENSOR[0], SENSOR[1], SENSOR[2]);
    let pts = room_scan(H, SENSOR, 100_000);
    // Zero-copy publish: fill the loaned shared-memory slice in place.
    let mut loan = pubr.loan(pts.len()).unwrap();
    loan.points_mut().copy_from_slice(&pts);
    // Frames are numbered from 1; wait for the snapshot of the second (the last).
    assert_eq!(loan.send(&pose, 1).unwrap(), 1);
    assert_eq!(pubr.publish(&pose, 2, &pts).unwrap(), 2);
    assert!(wait_for_seq(&mut sub, 2, 1000), "no snapshot with the room");

    let sample = sub.sample_bytes().unwrap().as_ptr_range();
    let view = sub.latest().unwrap().unwrap();
    // The view reads the shared-memory sample itself: no copy.
    let bytes = view.as_bytes().as_ptr_range();
    assert!(
        sample.start <= bytes.start && bytes.end <= sample.end,
        "view is not over the sample"
    );
    assert_eq!(view.resolution(), 0.05);
    // Walls occupied where points hit, interior free, outside unknown.
    for p in pts.iter().step_by(997) {
        let w = pose * nalgebra::Point3::new(p[0] as f64, p[1] as f64, p[2] as f64);
        assert_eq!(view.state_at(&w), VoxelState::Occupied, "{w:?}");
    }
    for x in [-1.5, -0.5, 0.0, 0.7, 1.6] {
        for y in [-1.1, 0.0, 1.1] {
            assert_eq!(
                view.state_at(&WorldPoint::new(x, y, 0.013)),
                VoxelState::Free,
                "({x}, {y})"
            );
        }
    }
    assert_eq!(
        view.state_at(&WorldPoint::new(H[0] + 0.5, 0.0, 0.0)),
        VoxelState::Unknown
    );
    // Planner queries: the line of sight across the room is clear; through a wall it hits.
    let c = WorldPoint::new(0.0, 0.0, 0.0);
    assert_eq!(
        view.first_hit(&c, &WorldPoint::new(1.5, 0.5, 0.2), true)
            .unwrap(),
        None
    );
    assert!(view
        .first_hit(&c, &WorldPoint::new(H[0] + 0.3, 0.0, 0.0), false)
        .unwrap()
        .is_some());
    assert_eq!(
        view.is_box_free(
            &WorldPoint::new(-0.5, -0.5, -0.3),
            &WorldPoint::new(0.5, 0.5, 0.3),
            false
        ),
        Ok(true)
    );
    let known = view.counts().0;

    // A late-joining planner gets the current snapshot at once.
    let mut late = connect_with_retry(|| SnapshotSubscriber::connect(&prefix, "default"));
    assert!(wait_for_seq(&mut late, 2, 1000), "late joiner got nothing");
    assert_eq!(late.latest().unwrap().unwrap().counts().0, known);

    // A frame whose header lies about its payload is rejected and changes nothing.
    let mut bad = pubr.loan(10).unwrap();
    *bad.header_mut() = voxmap_client::FrameHeader {
        sequence: 99,
        point_count: 11,
        ..Default::default()
    };
    bad.send_raw().unwrap();
    std::thread::sleep(Duration::from_millis(500));
    // iceoryx2 may hand this subscriber the history sample again when connections are
    // updated for the late joiner; what must not appear is a snapshot of the bad frame.
    sub.wait_for_update(Duration::from_millis(300)).unwrap();
    let after = sub.latest().unwrap().unwrap();
    assert_eq!(after.sequence(), 2, "a rejected frame must not publish");
    assert_eq!(after.counts().0, known);

    let (st, err) = svc.signal_and_wait("TERM");
    assert!(st.success(), "exit status {st:?}: {err}");
    assert!(
        err.contains("rejected: header says 11 points, payload holds 10"),
        "{err}"
    );
    assert!(
        err.contains("rejected 1 (point count mismatch 1);"),
        "stats count the rejection: {err}"
    );
}

#[test]
fn sigterm_saves_a_loadable_map() {
    let prefix = unique_prefix("save");
    let path = std::env::temp_dir().join(format!("{prefix}.vxm"));
    let Scanned { svc, known, .. } =
        start_and_scan(&prefix, &["--save-on-exit", path.to_str().unwrap()]);
    let (st, err) = svc.signal_and_wait("TERM");
    assert!(st.success(), "{err}");
    let map = voxmap_map::io::mapfile::load_map(&path).unwrap();
    let c = map.counts();
    assert_eq!(c.occupied + c.free, known);
    std::fs::remove_file(&path).unwrap();
}

#[test]
fn kill_9_then_restart_while_the_planner_keeps_its_snapshot() {
    let prefix = unique_prefix("kill");
    let Scanned {
        svc,
        mut sub,
        mut pubr,
        pose,
        known,
    } = start_and_scan(&prefix, &[]);

    let (st, _) = svc.signal_and_wait("KILL");
    assert!(!st.success());
    // The planner still reads the snapshot it holds.
    let view = sub.latest().unwrap().unwrap();
    assert_eq!(view.counts().0, known);
    assert_eq!(
        view.state_at(&WorldPoint::new(0.0, 0.0, 0.013)),
        VoxelState::Free
    );

    // A restart comes up despite the dead node's leftovers and serves the same planner.
    let t = Instant::now();
    let svc = Service::start(&prefix, &[]);
    pubr.publish(&pose, 1, &room_scan(H, SENSOR, 20_000))
        .unwrap();
    let deadline = Instant::now() + Duration::from_secs(30);
    let mut got = false;
    while Instant::now() < deadline && !got {
        // Frames sent before the new service subscribed are lost: keep sending.
        if sub.wait_for_update(Duration::from_millis(300)).unwrap() {
            got = sub.latest().unwrap().unwrap().counts().0 > 0;
        } else {
            pubr.publish(&pose, 2, &room_scan(H, SENSOR, 20_000))
                .unwrap();
        }
    }
    assert!(got, "restarted service never reached the planner");
    eprintln!("restart to first snapshot: {:?}", t.elapsed());
    let (st, err) = svc.signal_and_wait("TERM");
    assert!(st.success(), "{err}");
}

/// Random points in a ball of radius `r` (deterministic).
fn ball(n: usize, r: f64, seed: u64) -> Vec<[f32; 3]> {
    let mut rng = voxmap_tests::TestRng(seed);
    let mut f = move || rng.f() * 2.0 - 1.0;
    let mut v = Vec::with_capacity(n);
    while v.len() < n {
        let p = [f(), f(), f()];
        if p.iter().map(|c| c * c).sum::<f64>() <= 1.0 {
            v.push(p.map(|c| (c * r) as f32));
        }
    }
    v
}

#[test]
fn snapshots_grow_from_a_kilobyte_past_64_megabytes_without_failing() {
    let prefix = unique_prefix("grow");
    let svc = Service::start(&prefix, &["--snapshot-values", "--max-range", "30"]);
    let mut sub = connect_with_retry(|| SnapshotSubscriber::connect(&prefix, "default"));
    let mut pubr = connect_with_retry(|| FramePublisher::connect(&prefix, "default"));
    assert!(wait_for_seq(&mut sub, 0, 0));
    let first = sub.latest().unwrap().unwrap().as_bytes().len();
    assert!(first <= 1024, "empty map snapshot is {first} bytes");
    let mut sizes = vec![first];
    for (seq, n) in [(1u64, 200usize), (2, 2_000), (3, 20_000), (4, 40_000)] {
        let mut l = pubr.loan(n).unwrap();
        l.points_mut().copy_from_slice(&ball(n, 35.0, seq));
        *l.header_mut() = voxmap_client::FrameHeader {
            sequence: seq,
            point_count: n as u64,
            ..Default::default()
        };
        l.send_raw().unwrap();
        assert!(
            wait_for_seq(&mut sub, seq, 1),
            "no snapshot for frame {seq}"
        );
        let v = sub.latest().unwrap().unwrap();
        assert_eq!(v.sequence(), seq);
        sizes.push(v.as_bytes().len());
    }
    eprintln!("snapshot sizes: {sizes:?}");
    assert!(sizes.windows(2).all(|w| w[0] < w[1]), "{sizes:?}");
    assert!(
        *sizes.last().unwrap() > 64 << 20,
        "largest snapshot {sizes:?}"
    );
    let (st, err) = svc.signal_and_wait("TERM");
    assert!(st.success(), "{err}");
    assert!(err.contains("rejected 0;"), "{err}");
}

#[test]
fn a_slow_load_stalls_neither_frames_nor_requests() {
    use std::io::Write;
    use std::sync::mpsc::channel;
    use voxmap_client::MapControl;
    let prefix = unique_prefix("slowload");
    let Scanned {
        svc,
        mut sub,
        mut pubr,
        pose,
        known,
    } = start_and_scan(&prefix, &[]);
    let mut ctl = connect_with_retry(|| MapControl::connect(&prefix, "default"));
    ctl.set_timeout(Duration::from_secs(10));
    let dir = std::env::temp_dir();
    let saved = dir.join(format!("{prefix}.vxm"));
    ctl.save(saved.to_str().unwrap()).unwrap();
    ctl.clear().unwrap();

    // A load from a FIFO: the service's file worker blocks reading it until this test
    // writes the map file into it.
    let fifo = dir.join(format!("{prefix}.fifo"));
    let made = std::process::Command::new("mkfifo").arg(&fifo).status();
    assert!(made.unwrap().success());
    let (p, f) = (prefix.clone(), fifo.clone());
    let loader = std::thread::spawn(move || {
        let ctl = connect_with_retry(|| MapControl::connect(&p, "default"));
        ctl.load(f.to_str().unwrap())
    });
    // Opening a FIFO for writing returns once a reader has opened it: the load is running.
    let (opened_tx, opened) = channel();
    let (bytes_tx, bytes) = channel::<Vec<u8>>();
    let f = fifo.clone();
    std::thread::spawn(move || {
        let mut w = std::fs::OpenOptions::new().write(true).open(&f).unwrap();
        opened_tx.send(()).unwrap();
        w.write_all(&bytes.recv().unwrap()).unwrap();
    });
    opened
        .recv_timeout(Duration::from_secs(20))
        .expect("the service never opened the file to load");

    // While the load waits: a smaller scan is integrated and published, stats answered.
    pubr.publish(&pose, 1, &room_scan(H, SENSOR, 2_000))
        .unwrap();
    assert!(
        wait_for_seq(&mut sub, 1, 1),
        "frame not integrated during the load"
    );
    let partial = sub.latest().unwrap().unwrap().counts().0;
    assert!(partial > 0 && partial < known, "{partial} vs {known}");
    assert_eq!(ctl.stats().unwrap().frames_integrated, 2);
    assert!(!loader.is_finished());

    // A clear asked during the load is answered after it, and applies after it.
    let p = prefix.clone();
    let clearer = std::thread::spawn(move || {
        let ctl = connect_with_retry(|| MapControl::connect(&p, "default"));
        ctl.clear()
    });
    std::thread::sleep(Duration::from_millis(300));
    assert!(
        !clearer.is_finished(),
        "a clear was answered during the load"
    );

    bytes_tx.send(std::fs::read(&saved).unwrap()).unwrap();
    loader.join().unwrap().unwrap();
    clearer.join().unwrap().unwrap();
    let st = ctl.stats().unwrap();
    assert_eq!(st.map_leaves, 0, "the clear came after the load");
    assert_eq!(st.frames_integrated, 2);

    let (st, err) = svc.signal_and_wait("TERM");
    assert!(st.success(), "{err}");
    let _ = std::fs::remove_file(&saved);
    let _ = std::fs::remove_file(&fifo);
}

#[test]
fn control_requests_stats_save_clear_load_scope_and_bad_requests() {
    use voxmap_client::{ControlKind, ControlRequest, MapControl, MapScope};
    let prefix = unique_prefix("ctl");
    let Scanned {
        svc,
        mut sub,
        known,
        ..
    } = start_and_scan(&prefix, &[]);
    let ctl = connect_with_retry(|| MapControl::connect(&prefix, "default"));

    let st = ctl.stats().unwrap();
    // The stats name the kernel the service runs: this CPU's best.
    assert_eq!(st.kernel(), voxmap_map::Kernel::detect().name());
    assert_eq!(
        (
            st.frames_received,
            st.frames_integrated,
            st.points_integrated
        ),
        (1, 1, 20_000)
    );
    assert!(st.integrate_ms_p50 > 0.0 && st.map_leaves > 0 && st.snapshot_bytes > 0);

    let dir = std::env::temp_dir();
    let saved = dir.join(format!("{prefix}.vxm"));
    ctl.save(saved.to_str().unwrap()).unwrap();
    ctl.clear().unwrap();
    assert!(wait_for_seq(&mut sub, 0, 0));
    assert_eq!(
        sub.latest().unwrap().unwrap().counts().0,
        0,
        "cleared map publishes an empty snapshot"
    );

    // A corrupt file is refused and the (empty) map stays as it is.
    let bad = dir.join(format!("{prefix}.bad.vxm"));
    std::fs::write(&bad, b"VXMMAP\0\0garbage").unwrap();
    let e = ctl.load(bad.to_str().unwrap()).unwrap_err().to_string();
    assert!(
        e.contains("unsupported map file version") || e.contains("corrupt"),
        "{e}"
    );
    assert_eq!(ctl.stats().unwrap().map_leaves, 0);

    ctl.load(saved.to_str().unwrap()).unwrap();
    let deadline = Instant::now() + Duration::from_secs(10);
    while sub.latest().unwrap().unwrap().counts().0 != known && Instant::now() < deadline {
        sub.wait_for_update(Duration::from_millis(100)).unwrap();
    }
    assert_eq!(
        sub.latest().unwrap().unwrap().counts().0,
        known,
        "loaded map is published"
    );

    // Scope: a 1 m box around the sensor holds fewer voxels than the whole room.
    ctl.set_scope(MapScope::AroundSensor {
        half_extents: [0.5, 0.5, 0.5],
    })
    .unwrap();
    let deadline = Instant::now() + Duration::from_secs(10);
    while sub.latest().unwrap().unwrap().counts().0 == known && Instant::now() < deadline {
        sub.wait_for_update(Duration::from_millis(100)).unwrap();
    }
    let boxed = sub.latest().unwrap().unwrap().counts().0;
    assert!(boxed > 0 && boxed < known / 4, "{boxed} of {known}");
    assert!(ctl
        .set_scope(MapScope::AroundSensor {
            half_extents: [-1.0, 1.0, 1.0]
        })
        .is_err());

    // Unknown and malformed requests get errors; the service carries on.
    let r = ctl
        .request(ControlRequest {
            kind: 99,
            ..ControlRequest::new(ControlKind::Stats)
        })
        .unwrap();
    assert_eq!((r.ok, r.message()), (0, "unknown request kind 99"));
    let r = ctl
        .request(ControlRequest {
            path_len: 9999,
            ..ControlRequest::new(ControlKind::Save)
        })
        .unwrap();
    assert_eq!(r.ok, 0);
    assert_eq!(ctl.stats().unwrap().frames_integrated, 1);

    let (st, err) = svc.signal_and_wait("TERM");
    assert!(st.success(), "{err}");
    let _ = std::fs::remove_file(&saved);
    let _ = std::fs::remove_file(&bad);
}

#[test]
fn config_file_and_queue_intake_integrate_a_burst_in_order() {
    use voxmap_client::MapControl;
    let prefix = unique_prefix("queue");
    let cfg = std::env::temp_dir().join(format!("{prefix}.toml"));
    // The file sets the resolution and the queue; the flag overrides the depth.
    std::fs::write(
        &cfg,
        "resolution = 0.2\nintake = \"queue\"\nqueue_depth = 4\n",
    )
    .unwrap();
    let Scanned {
        svc,
        mut sub,
        mut pubr,
        pose,
        ..
    } = start_and_scan(
        &prefix,
        &["--config", cfg.to_str().unwrap(), "--queue-depth", "2"],
    );
    assert_eq!(sub.latest().unwrap().unwrap().resolution(), 0.2);
    let ctl = connect_with_retry(|| MapControl::connect(&prefix, "default"));
    // A burst of 12 frames: a queue of 2 keeps the newest waiting frames, so some are
    // dropped; every frame is either integrated or counted as dropped, and the last
    // snapshot holds the last frame.
    let scan = room_scan(H, SENSOR, 2_000);
    let mut last = 0;
    for _ in 0..12 {
        last = pubr.publish(&pose, 0, &scan).unwrap();
    }
    assert!(
        wait_for_seq(&mut sub, last, 0),
        "last frame never published"
    );
    let s = ctl.stats().unwrap();
    assert_eq!(s.frames_integrated + s.frames_dropped, 13, "{s:?}");
    assert!(s.frames_integrated >= 3, "{s:?}");
    assert_eq!(s.frames_rejected, 0);
    drop(svc);
    std::fs::remove_file(&cfg).unwrap();
}

/// A held snapshot (what the C and Python views keep) stays valid and unchanged while the
/// service publishes newer ones; a subscriber holding one old snapshot besides its newest
/// still receives; the shared memory is not copied.
#[test]
fn held_snapshots_stay_unchanged_while_newer_ones_arrive() {
    let prefix = unique_prefix("held");
    let mut s = start_and_scan(&prefix, &[]);
    let old = s.sub.latest_held().unwrap().unwrap();
    let (old_seq, old_copy) = (old.view().sequence(), old.view().as_bytes().to_vec());
    let sample = s.sub.sample_bytes().unwrap().as_ptr_range();
    assert!(
        sample.contains(&old.view().as_bytes().as_ptr()),
        "held view is a copy"
    );
    let mut newest = old_seq;
    for k in 0..4u64 {
        let pose = Isometry3::translation(SENSOR[0] + 0.1 * k as f64, SENSOR[1], SENSOR[2]);
        let seq = s
            .pubr
            .publish(&pose, 0, &room_scan(H, SENSOR, 5_000))
            .unwrap();
        assert!(
            wait_for_seq(&mut s.sub, seq, 1),
            "no snapshot of frame {seq}"
        );
        // The newest, held too (as a planner keeping its view while it plans), then let go.
        let held = s.sub.latest_held().unwrap().unwrap();
        assert!(held.view().sequence() > newest);
        newest = held.view().sequence();
        assert_eq!(old.view().sequence(), old_seq);
        assert_eq!(
            old.view().as_bytes(),
            &old_copy[..],
            "a held snapshot changed"
        );
    }
    drop(old);
    assert_eq!(s.sub.latest().unwrap().unwrap().sequence(), newest);
    drop(s.svc);
}

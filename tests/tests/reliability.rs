//! The service against a hostile publisher: frames with random header fields and payload
//! sizes (zero points, the limit, lying counts, non-finite and huge coordinates, non-unit
//! and zero quaternions, unknown versions, origins outside the map) mixed with good frames.
//! `VOXMAP_HOSTILE_FRAMES` sets how many (CI: the default; the figures in
//! docs/reliability.md: 1,000,000).

use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
use std::collections::BTreeMap;
use std::time::Duration;
use voxmap_client::{FrameHeader, FramePublisher, MapControl, FRAME_VERSION, MAX_FRAME_POINTS};
use voxmap_map::io::mapfile;
use voxmap_map::{Frame, FrameStamp, IntegratorConfig, Mapper, MapperConfig};
use voxmap_tests::{
    connect_with_retry, room_scan, tmpdir, unique_prefix, voxels, voxmap_bin, Service, TestRng,
};

const DEFAULT_FRAMES: u64 = 20_000;

/// What is wrong with a frame (`None`: nothing), named as the service counts it.
const DEFECTS: [&str; 6] = [
    "unsupported version",
    "point count mismatch",
    "too many points",
    "pose not finite",
    "quaternion not unit",
    "origin out of range",
];

/// A good frame: a room scan from one of a few poses, sometimes with hostile points in
/// its payload (NaN, infinite and huge coordinates), which the service must skip or cut.
fn good_frame(rng: &mut TestRng) -> (Isometry3<f64>, Vec<[f32; 3]>) {
    let k = rng.below(6) as f64;
    let sensor = [0.2 * k - 0.5, 0.1 * k - 0.3, 0.05 * k];
    let mut pts = room_scan([2.0, 1.5, 1.2], sensor, 500 + rng.below(1500) as usize);
    if rng.below(3) == 0 {
        for _ in 0..rng.below(50) {
            let i = rng.below(pts.len() as u64) as usize;
            pts[i] = match rng.below(4) {
                0 => [f32::NAN, 0.0, 1.0],
                1 => [f32::INFINITY, -1.0, 0.0],
                2 => [1e30, -1e30, 3e38],
                _ => [f32::MIN_POSITIVE, 0.0, -0.0],
            };
        }
    }
    let pose = Isometry3::from_parts(
        Translation3::new(sensor[0], sensor[1], sensor[2]),
        UnitQuaternion::from_axis_angle(&Vector3::z_axis(), 0.3 * k),
    );
    (pose, pts)
}

/// A header with random sequence, stamp and flags, and the pose of `pose`.
fn random_header(rng: &mut TestRng, pose: &Isometry3<f64>, n: u64) -> FrameHeader {
    FrameHeader {
        flags: rng.next_u64() as u32,
        sequence: rng.next_u64(),
        timestamp_ns: rng.next_u64(),
        point_count: n,
        ..FrameHeader::with_pose(pose)
    }
}

/// Make `h` wrong in the way `defect` says, and only in that way.
fn spoil(rng: &mut TestRng, h: &mut FrameHeader, defect: usize, payload: u64) {
    let wild = |rng: &mut TestRng| match rng.below(4) {
        0 => f64::NAN,
        1 => f64::INFINITY,
        2 => f64::NEG_INFINITY,
        _ => f64::from_bits(0x7ff0_0000_0000_0001 | rng.next_u64() >> 13),
    };
    match defect {
        0 => {
            h.version = rng.next_u64() as u32;
            if h.version == FRAME_VERSION {
                h.version ^= 1;
            }
        }
        1 => h.point_count = payload + 1 + rng.below(MAX_FRAME_POINTS - payload),
        2 => h.point_count = MAX_FRAME_POINTS + 1 + rng.below(u64::MAX - MAX_FRAME_POINTS - 1),
        3 => {
            let i = rng.below(7) as usize;
            if i < 3 {
                h.translation[i] = wild(rng);
            } else {
                h.rotation_xyzw[i - 3] = wild(rng);
            }
        }
        4 => {
            let s = [0.0, 0.5, 2.0, 1e300][rng.below(4) as usize];
            h.rotation_xyzw = h.rotation_xyzw.map(|c| c * s);
        }
        _ => h.translation[rng.below(3) as usize] = 1e12 * (rng.f() + 0.5),
    }
}

#[test]
fn a_hostile_publisher_changes_nothing_but_its_good_frames() {
    let total: u64 = std::env::var("VOXMAP_HOSTILE_FRAMES")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(DEFAULT_FRAMES);
    let prefix = unique_prefix("hostile");
    let args = ["--resolution", "0.1", "--max-range", "10", "--threads", "2"];
    let queue = ["--intake", "queue", "--queue-depth", "4"];
    let svc = Service::spawn(&prefix, &[&args[..], &queue].concat(), &[]);
    let mut pubr = connect_with_retry(|| FramePublisher::connect(&prefix, "default"));
    let mut control = connect_with_retry(|| MapControl::connect(&prefix, "default"));
    control.set_timeout(Duration::from_secs(20));

    let mut rng = TestRng(0x5eed_1234);
    let mut good = Vec::new();
    let mut sent_bad: BTreeMap<&str, u64> = BTreeMap::new();
    let mut sent = 0u64;
    // Once: a payload at the limit of points, with a wrong version.
    {
        let mut l = pubr.loan(MAX_FRAME_POINTS as usize).unwrap();
        let mut h = random_header(&mut rng, &Isometry3::identity(), MAX_FRAME_POINTS);
        spoil(&mut rng, &mut h, 0, MAX_FRAME_POINTS);
        *l.header_mut() = h;
        l.send_raw().unwrap();
        sent += 1;
        *sent_bad.entry(DEFECTS[0]).or_default() += 1;
    }
    while sent < total {
        if rng.below(100) == 0 {
            let (pose, pts) = good_frame(&mut rng);
            let mut l = pubr.loan(pts.len()).unwrap();
            l.points_mut().copy_from_slice(&pts);
            *l.header_mut() = random_header(&mut rng, &pose, pts.len() as u64);
            l.send_raw().unwrap();
            good.push((pose, pts));
        } else {
            // Mostly small payloads, some empty; points anything at all.
            let n = match rng.below(8) {
                0 => 0,
                _ => rng.below(64),
            };
            let defect = rng.below(DEFECTS.len() as u64) as usize;
            let mut l = pubr.loan(n as usize).unwrap();
            for p in l.points_mut() {
                *p = [0; 3].map(|_| f32::from_bits(rng.next_u64() as u32));
            }
            let pose = Isometry3::from_parts(
                Translation3::new(rng.f(), rng.f(), rng.f()),
                UnitQuaternion::from_euler_angles(rng.f(), rng.f(), rng.f()),
            );
            let mut h = random_header(&mut rng, &pose, n);
            spoil(&mut rng, &mut h, defect, n);
            *l.header_mut() = h;
            l.send_raw().unwrap();
            *sent_bad.entry(DEFECTS[defect]).or_default() += 1;
        }
        sent += 1;
        // At most the queue's depth waits at once, so none is lost and every one is
        // validated: wait until the service has taken all sent (a request can be answered
        // just before the last frames are taken). A stalled service fails here.
        if sent.is_multiple_of(4) || sent == total {
            let deadline = std::time::Instant::now() + Duration::from_secs(20);
            let s = loop {
                let s = match control.stats() {
                    Ok(s) => s,
                    Err(e) => {
                        let pid = svc.child.id();
                        let count = |what: &str| {
                            std::fs::read_dir(format!("/proc/{pid}/{what}"))
                                .map_or(0, |d| d.count())
                        };
                        let maps = std::fs::read_to_string(format!("/proc/{pid}/maps"))
                            .map_or(0, |m| m.lines().count());
                        eprintln!(
                            "service pid {pid}: {} fds, {maps} mappings, {} threads",
                            count("fd"),
                            count("task")
                        );
                        let (_, log) = svc.signal_and_wait("INT");
                        let tail: Vec<&str> = log.lines().rev().take(12).collect();
                        panic!("no answer after {sent} frames: {e:?}; service log (last lines first): {tail:#?}");
                    }
                };
                assert!(s.frames_received <= sent);
                if s.frames_received == sent {
                    break s;
                }
                assert!(
                    std::time::Instant::now() < deadline,
                    "stalled at {sent}: {s:?}"
                );
            };
            assert_eq!(s.frames_integrated, good.len() as u64);
        }
    }
    let s = control.stats().unwrap();
    assert_eq!(s.frames_rejected, sent - good.len() as u64);
    let saved = tmpdir("hostile").join("m.map");
    control.save(saved.to_str().unwrap()).unwrap();
    let (status, log) = svc.signal_and_wait("INT");
    assert!(status.success(), "{log}");

    // Rejections counted by reason, exactly as sent.
    let exit = log.lines().rfind(|l| l.contains("exiting;")).unwrap();
    for (k, n) in &sent_bad {
        assert!(exit.contains(&format!("{k} {n}")), "{k} {n}: {exit}");
    }
    // The log names a few rejections, not each.
    let logged = log.lines().filter(|l| l.contains(" rejected: ")).count() as u64;
    assert!(
        logged <= 5 + sent / 1000,
        "{logged} lines for {sent} frames"
    );

    // The map is the good frames' map, integrated here in the same order.
    let mut mapper = Mapper::new(&MapperConfig {
        integrator: IntegratorConfig {
            threads: 2,
            max_range: 10.0,
            ..Default::default()
        },
        ..Default::default()
    })
    .unwrap();
    for (i, (pose, pts)) in good.iter().enumerate() {
        let frame = Frame {
            pose: *pose,
            points: pts,
        };
        let stamp = FrameStamp {
            sequence: i as u64 + 1,
            stamp_ns: 0,
        };
        mapper.insert(&frame, stamp).unwrap();
    }
    let map = mapper.map();
    let served = mapfile::load_map(&saved).unwrap();
    assert!(!good.is_empty());
    assert_eq!(voxels(&served), voxels(map));
    eprintln!(
        "hostile publisher: {sent} frames ({} good, {} bad by reason {sent_bad:?}), all received, every bad one rejected, the map equal to the good frames' map",
        good.len(),
        sent - good.len() as u64
    );
}

/// A control request sent before the service is up (a planner started first, or a
/// service restarting after a crash) is answered once the service is there, instead of
/// waiting out its timeout for a server that never saw it.
#[test]
fn a_request_sent_before_the_service_starts_is_answered() {
    // Built first: a binary older than the sources is rebuilt on first use, which can take
    // longer than the request's timeout.
    voxmap_bin();
    let prefix = unique_prefix("early");
    // The control service exists from the client's side only: no server has it yet.
    let mut c = MapControl::connect(&prefix, "default").unwrap();
    c.set_timeout(Duration::from_secs(20));
    let starter = {
        let prefix = prefix.clone();
        std::thread::spawn(move || {
            std::thread::sleep(Duration::from_millis(300));
            Service::start(&prefix, &[])
        })
    };
    let s = c.stats().expect("answered once the service was up");
    let _svc = starter.join().unwrap();
    assert_eq!(s.frames_received, 0);
}

/// Who may connect: iceoryx2 (built without its `dev_permissions` feature) creates the
/// service's shared memory, event sockets and node files for their owner alone, so only
/// processes of the service's user can publish frames, read snapshots or send requests
/// (iceoryx2's global node counter is the one file open to all). A dependency that turned
/// on world access would fail here.
#[test]
fn shared_memory_and_sockets_are_for_the_owner_alone() {
    use std::os::unix::fs::{FileTypeExt, MetadataExt};
    let prefix = unique_prefix("modes");
    let _svc = Service::start(&prefix, &[]);
    let c = connect_with_retry(|| MapControl::connect(&prefix, "default"));
    c.stats().unwrap();
    let me = std::fs::metadata("/proc/self").unwrap().uid();
    let mut checked = 0;
    let mut stack = vec![
        std::path::PathBuf::from("/dev/shm"),
        std::path::PathBuf::from("/tmp/iceoryx2"),
    ];
    while let Some(dir) = stack.pop() {
        for e in std::fs::read_dir(&dir).unwrap().flatten() {
            let name = e.file_name().to_string_lossy().into_owned();
            let Ok(m) = e.metadata() else { continue }; // removed meanwhile
            if m.uid() != me || !(dir.starts_with("/tmp/iceoryx2") || name.starts_with("iox2_")) {
                continue;
            }
            let mode = m.mode() & 0o777;
            if m.is_dir() {
                // Directories: others may at most look in; nobody but the owner writes.
                assert_eq!(
                    mode & 0o022,
                    0,
                    "{} is writable by others: {mode:o}",
                    e.path().display()
                );
                stack.push(e.path());
            } else if name.ends_with(".global_mgmt") {
                // The one exception, by iceoryx2's design: a 16-byte node counter shared
                // by every user of the machine (`node.<version>.global_mgmt`), world
                // writable so that node ids stay unique across users. It holds no data.
                assert!(m.len() <= 64, "{name}: {} bytes", m.len());
            } else {
                assert_eq!(
                    mode & 0o077,
                    0,
                    "{} is open to others: {mode:o}",
                    e.path().display()
                );
                assert!(m.is_file() || m.file_type().is_socket());
            }
            checked += 1;
        }
    }
    // The service's frames, snapshots, control and events, at the least.
    assert!(checked >= 8, "only {checked} iceoryx2 files found");
}

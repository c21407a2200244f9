//! The C, C++ and Python APIs against the Rust view, on the same map: every query answered
//! through each equals the Rust answer; mutated snapshot bytes never crash a C caller; and a
//! frame published from C++ and one from Python both come back in the snapshots read from
//! C++ and from Python, through a live `voxmap serve`.
//!
//! Needs cmake and a C++ compiler (the C package is built and installed into
//! `target/c-prefix`, or taken from `VOXMAP_C_PREFIX`) and a Python with `voxmap` and
//! `pytest` (`VOXMAP_PYTHON`, after `pip install ./python pytest`); `.ci/run` sets up both.
//! Without them the tests say so and pass, unless `VOXMAP_REQUIRE_FOREIGN` is set (CI),
//! which makes that a failure.

use nalgebra::{Isometry3, Translation3, UnitQuaternion};
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};
use voxmap_client::SnapshotSubscriber;
use voxmap_map::io::mapfile;
use voxmap_map::snapshot::{Nearest, SnapshotView};
use voxmap_map::{Frame, FrameStamp, IntegratorConfig, Mapper, MapperConfig, WorldPoint};
use voxmap_tests::{room_scan, run_ok, tmpdir, unique_prefix, Service};

const REPO: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/..");

fn required() -> bool {
    std::env::var_os("VOXMAP_REQUIRE_FOREIGN").is_some()
}

/// The installed C package: `VOXMAP_C_PREFIX`, else `c/` built and installed into
/// `target/c-prefix` by cmake (once per test process); `None` (with a notice) without cmake.
fn c_prefix() -> Option<PathBuf> {
    static BUILT: std::sync::OnceLock<Option<PathBuf>> = std::sync::OnceLock::new();
    BUILT
        .get_or_init(|| {
            if let Some(p) = std::env::var_os("VOXMAP_C_PREFIX") {
                let p = PathBuf::from(p);
                assert!(
                    p.join("include/voxmap.hpp").exists(),
                    "VOXMAP_C_PREFIX={} holds no installed voxmap",
                    p.display()
                );
                return Some(p);
            }
            let tools = ["cmake", "c++"]
                .iter()
                .all(|t| Command::new(t).arg("--version").output().is_ok());
            if !tools {
                assert!(!required(), "no cmake or C++ compiler");
                eprintln!("NOTICE: no cmake or C++ compiler: skipping the C/C++ tests");
                return None;
            }
            let target = PathBuf::from(format!("{REPO}/target"));
            let prefix = target.join("c-prefix");
            cmake_build("c", &prefix, &target.join("c-build"));
            let build = target.join("c-build");
            run_ok(
                Command::new("cmake")
                    .arg("--install")
                    .arg(&build)
                    .arg("--prefix")
                    .arg(&prefix),
            );
            Some(prefix)
        })
        .clone()
}

/// A Python that imports `voxmap` and `pytest`, or `None` (with a notice).
fn python_api() -> Option<PathBuf> {
    voxmap_tests::python_with(
        "voxmap, pytest, numpy",
        "VOXMAP_REQUIRE_FOREIGN",
        "pip install ./python pytest",
        "the Python API tests",
    )
}

/// Configure and build the CMake project `src` against the package in `prefix`.
fn cmake_build(src: &str, prefix: &Path, build: &Path) {
    let run = |args: &[&str]| {
        let out = Command::new("cmake").args(args).output().expect("cmake");
        assert!(
            out.status.success(),
            "cmake {args:?}:\n{}\n{}",
            String::from_utf8_lossy(&out.stdout),
            String::from_utf8_lossy(&out.stderr)
        );
    };
    let (src, build) = (format!("{REPO}/{src}"), build.to_str().unwrap().to_string());
    run(&[
        "-S",
        &src,
        "-B",
        &build,
        &format!("-DCMAKE_PREFIX_PATH={}", prefix.display()),
        "-DCMAKE_BUILD_TYPE=Release",
    ]);
    run(&["--build", &build, "-j", "2"]);
}

/// A small deterministic generator for the queries.
struct Rng(u64);
impl Rng {
    fn f(&mut self) -> f64 {
        self.0 ^= self.0 << 13;
        self.0 ^= self.0 >> 7;
        self.0 ^= self.0 << 17;
        (self.0 >> 11) as f64 / (1u64 << 53) as f64
    }
    fn within(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * self.f()
    }
}

/// A map of two room scans and random clutter, its map file, and the queries.
struct Fixture {
    dir: PathBuf,
    map: PathBuf,
    snapshot: PathBuf,
    queries: PathBuf,
    expected: PathBuf,
}

fn fixture(name: &str) -> Fixture {
    let dir = tmpdir(name);
    // 2.5 cm voxels: a snapshot over 512 KiB, where the batched queries take their staged
    // path (below, they answer one point at a time).
    let mut mapper = Mapper::new(&MapperConfig {
        resolution: 0.025,
        integrator: IntegratorConfig {
            threads: 2,
            max_range: 8.0,
            ..Default::default()
        },
        ..Default::default()
    })
    .unwrap();
    let mut seq = 0;
    let mut insert = |pose, pts: &[[f32; 3]]| {
        seq += 1;
        let stamp = FrameStamp {
            sequence: seq,
            stamp_ns: seq,
        };
        mapper.insert(&Frame { pose, points: pts }, stamp).unwrap();
    };
    let h = [3.0, 2.0, 1.5];
    for sensor in [[0.5, -0.3, 0.2], [-1.2, 0.8, -0.4]] {
        let pose = Isometry3::translation(sensor[0], sensor[1], sensor[2]);
        let pts = room_scan(h, sensor, 60_000);
        insert(pose, &pts);
    }
    let mut rng = Rng(0x2545F4914F6CDD1D);
    for _ in 0..3 {
        let pose = Isometry3::from_parts(
            Translation3::new(rng.within(-1.0, 1.0), rng.within(-1.0, 1.0), 0.0),
            UnitQuaternion::from_euler_angles(0.0, 0.0, rng.within(0.0, 6.0)),
        );
        let pts: Vec<[f32; 3]> = (0..5000)
            .map(|_| [0, 1, 2].map(|k| rng.within(-h[k], h[k]) as f32))
            .collect();
        insert(pose, &pts);
    }
    let (map, _) = mapper.into_parts();
    let map_path = dir.join("map.vxm");
    mapfile::save_map(&map, &map_path).unwrap();
    let snap = mapfile::read_as_snapshot(&map_path).unwrap();
    assert!(snap.len() > 512 << 10, "a {} byte snapshot", snap.len());
    let snapshot = dir.join("map.snap");
    mapfile::save_snapshot(&snap, &snapshot).unwrap();

    // Points, rays and boxes over the room and beyond it, and some that are not valid.
    let span = |rng: &mut Rng| [0, 1, 2].map(|k| rng.within(-h[k] - 1.0, h[k] + 1.0));
    let mut points: Vec<[f64; 3]> = (0..20_000).map(|_| span(&mut rng)).collect();
    points.extend([
        [f64::NAN, 0.0, 0.0],
        [1e12, 0.0, 0.0],
        [0.0, f64::INFINITY, 1.0],
    ]);
    let mut rays: Vec<[f64; 7]> = (0..3000)
        .map(|i| {
            let (a, b) = (span(&mut rng), span(&mut rng));
            [a[0], a[1], a[2], b[0], b[1], b[2], f64::from(i % 2)]
        })
        .collect();
    rays.push([f64::NAN, 0.0, 0.0, 1.0, 1.0, 1.0, 0.0]);
    rays.push([0.0, 0.0, 0.0, 1e5, 0.0, 0.0, 0.0]);
    let mut boxes: Vec<[f64; 7]> = (0..3000)
        .map(|i| {
            let c = span(&mut rng);
            let e = [0, 1, 2].map(|_| rng.within(0.0, 0.6));
            [
                c[0] - e[0],
                c[1] - e[1],
                c[2] - e[2],
                c[0] + e[0],
                c[1] + e[1],
                c[2] + e[2],
                f64::from(i % 2),
            ]
        })
        .collect();
    boxes.push([1.0, 0.0, 0.0, 0.0, 1.0, 1.0, 1.0]);
    boxes.push([f64::NAN, 0.0, 0.0, 1.0, 1.0, 1.0, 1.0]);
    let mut q = Vec::new();
    let block = |q: &mut Vec<u8>, n: usize, vals: &mut dyn Iterator<Item = f64>| {
        q.extend((n as u64).to_le_bytes());
        vals.for_each(|v| q.extend(v.to_le_bytes()));
    };
    block(&mut q, points.len(), &mut points.iter().flatten().copied());
    block(&mut q, rays.len(), &mut rays.iter().flatten().copied());
    block(&mut q, boxes.len(), &mut boxes.iter().flatten().copied());
    let queries = dir.join("queries.bin");
    std::fs::write(&queries, q).unwrap();

    let view = SnapshotView::open(&snap).unwrap();
    let expected = dir.join("expected.bin");
    std::fs::write(&expected, answers(&view, &points, &rays, &boxes)).unwrap();
    Fixture {
        dir,
        map: map_path,
        snapshot,
        queries,
        expected,
    }
}

/// The Rust view's answers, laid out as `c/tests/programs/queries.cpp` writes them.
fn answers(
    v: &SnapshotView,
    points: &[[f64; 3]],
    rays: &[[f64; 7]],
    boxes: &[[f64; 7]],
) -> Vec<u8> {
    const INVALID: i32 = -2; // VOXMAP_ERR_INVALID
    let mut o = Vec::new();
    o.extend(v.resolution().to_le_bytes());
    let (known, occupied) = v.counts();
    o.extend(known.to_le_bytes());
    o.extend(occupied.to_le_bytes());
    let r = v.resolution();
    let (code, lo, hi) = match v.bounds() {
        Some((lo, hi)) => (
            1i32,
            lo.to_array().map(|c| f64::from(c) * r),
            hi.to_array().map(|c| (f64::from(c) + 1.0) * r),
        ),
        None => (0, [0.0; 3], [0.0; 3]),
    };
    o.extend(code.to_le_bytes());
    lo.iter().chain(&hi).for_each(|c| o.extend(c.to_le_bytes()));
    let wp: Vec<WorldPoint> = points.iter().map(|p| WorldPoint::from(*p)).collect();
    let mut states = Vec::new();
    v.states_at(&wp, &mut states);
    o.extend(states.iter().map(|s| *s as u8));
    o.extend(wp.iter().map(|p| v.state_at(p) as u8));
    for p in &wp {
        let prob = v.transform().voxel_of(p).and_then(|c| v.probability(c));
        o.extend(i32::from(prob.is_some()).to_le_bytes());
        o.extend(prob.unwrap_or(0.0).to_le_bytes());
    }
    for r in rays {
        let (a, b) = (
            WorldPoint::new(r[0], r[1], r[2]),
            WorldPoint::new(r[3], r[4], r[5]),
        );
        let (code, c) = match v.first_hit(&a, &b, r[6] != 0.0) {
            Ok(Some(hit)) => {
                let c = v.transform().voxel_center(hit);
                (1i32, [c.x, c.y, c.z])
            }
            Ok(None) => (0, [0.0; 3]),
            Err(_) => (INVALID, [0.0; 3]),
        };
        o.extend(code.to_le_bytes());
        c.iter().for_each(|x| o.extend(x.to_le_bytes()));
    }
    for b in boxes {
        let (lo, hi) = (
            WorldPoint::new(b[0], b[1], b[2]),
            WorldPoint::new(b[3], b[4], b[5]),
        );
        let code = match v.is_box_free(&lo, &hi, b[6] != 0.0) {
            Ok(free) => i32::from(free),
            Err(_) => INVALID,
        };
        o.extend(code.to_le_bytes());
    }
    let (mut n, mut sum) = (0u64, [0.0f64; 3]);
    for c in v.occupied_centers() {
        n += 1;
        (0..3).for_each(|k| sum[k] += c[k]);
    }
    o.extend(n.to_le_bytes());
    sum.iter().for_each(|x| o.extend(x.to_le_bytes()));
    o
}

#[test]
fn c_and_cpp_answer_as_the_rust_view_and_survive_mutated_snapshots() {
    let Some(prefix) = c_prefix() else { return };
    let f = fixture("c_api");
    let build = f.dir.join("build");
    cmake_build("c/tests/programs", &prefix, &build);
    // Both inputs: the map file (converted on open) and the snapshot file.
    for input in [&f.map, &f.snapshot] {
        let out = f.dir.join("cpp.bin");
        let said = run_ok(Command::new(build.join("queries")).args([input, &f.queries, &out]));
        // CI installs Eigen, so the Eigen overloads are compiled and checked there.
        if required() {
            assert!(said.contains("eigen overloads checked"), "{said}");
        }
        let (got, want) = (
            std::fs::read(&out).unwrap(),
            std::fs::read(&f.expected).unwrap(),
        );
        assert_eq!(got.len(), want.len(), "answer layouts differ");
        if let Some(i) = (0..got.len()).find(|&i| got[i] != want[i]) {
            panic!(
                "C++ answer differs from Rust's at byte {i} of {}",
                want.len()
            );
        }
    }
    let out =
        run_ok(Command::new(build.join("c_checks")).args([f.snapshot.to_str().unwrap(), "10000"]));
    let opened: u64 = out
        .trim()
        .strip_prefix("ok ")
        .and_then(|s| s.split_whitespace().next())
        .and_then(|n| n.parse().ok())
        .unwrap_or_else(|| panic!("c_checks: {out}"));
    // Mutations that leave the structure valid open and are queried, the rest are refused.
    eprintln!("c_checks: {opened} of 10000 mutated snapshots opened and were queried");
    assert!(
        opened > 100 && opened < 10_000,
        "{opened} of 10000 mutated snapshots opened"
    );
    std::fs::remove_dir_all(&f.dir).unwrap();
}

/// A snapshot file with the fixture map's distance field, points around and beyond it, and
/// the Rust field's answers in the layout of `c/tests/programs/field.cpp`.
fn field_fixture(f: &Fixture) -> (PathBuf, PathBuf, PathBuf) {
    let cfg = voxmap_map::field::FieldConfig {
        max_distance: 0.3,
        ..Default::default()
    };
    let snap = mapfile::read_as_snapshot_with_field(&f.map, &cfg).unwrap();
    let snapshot = f.dir.join("field.snap");
    mapfile::save_snapshot(&snap, &snapshot).unwrap();
    let view = SnapshotView::open(&snap).unwrap();
    let field = view.distance_field().expect("a field");
    let mut rng = Rng(0x9E3779B97F4A7C15);
    let mut points: Vec<[f64; 3]> = (0..5000)
        .map(|i| {
            // Half near the walls (the band), half anywhere.
            let h = [3.0, 2.0, 1.5];
            let mut p = [0, 1, 2].map(|k| rng.within(-h[k] - 0.5, h[k] + 0.5));
            if i % 2 == 0 {
                let k = i % 3;
                p[k] = h[k] * if rng.f() < 0.5 { -1.0 } else { 1.0 } + rng.within(-0.4, 0.4);
            }
            p
        })
        .collect();
    points.extend([[f64::NAN, 0.0, 0.0], [1e12, 0.0, 0.0], [0.0, 0.0, 50.0]]);
    let mut q = (points.len() as u64).to_le_bytes().to_vec();
    points
        .iter()
        .flatten()
        .for_each(|v| q.extend(v.to_le_bytes()));
    let pts = f.dir.join("field_points.bin");
    std::fs::write(&pts, q).unwrap();
    let mut o = field.max_distance().to_le_bytes().to_vec();
    let wp: Vec<WorldPoint> = points.iter().map(|p| WorldPoint::from(*p)).collect();
    for p in &wp {
        let d = field.distance_and_gradient_at(p);
        o.extend(i32::from(d.is_some()).to_le_bytes());
        let (d, g) = d.map_or((0.0, [0.0; 3]), |(d, g)| (d, [g.x, g.y, g.z]));
        o.extend(d.to_le_bytes());
        g.iter().for_each(|x| o.extend(x.to_le_bytes()));
        let (code, c, dist) = match field.nearest_obstacle(p) {
            Nearest::Unknown => (0i32, [0.0; 3], 0.0),
            Nearest::NoneWithin => (2, [0.0; 3], 0.0),
            Nearest::At {
                centre, distance, ..
            } => (1, [centre.x, centre.y, centre.z], distance),
        };
        o.extend(code.to_le_bytes());
        c.iter().for_each(|x| o.extend(x.to_le_bytes()));
        o.extend(dist.to_le_bytes());
    }
    let mut batched = Vec::new();
    field.distances_and_gradients_at(&wp, &mut batched);
    batched
        .iter()
        .flatten()
        .for_each(|x| o.extend(x.to_le_bytes()));
    let expected = f.dir.join("field_expected.bin");
    std::fs::write(&expected, o).unwrap();
    (snapshot, pts, expected)
}

#[test]
fn distance_field_from_cpp_and_python_answers_as_the_rust_view() {
    let Some(prefix) = c_prefix() else { return };
    let f = fixture("c_field");
    let (snapshot, pts, expected) = field_fixture(&f);
    let build = f.dir.join("build");
    cmake_build("c/tests/programs", &prefix, &build);
    let out = f.dir.join("field_cpp.bin");
    run_ok(Command::new(build.join("field")).args([&snapshot, &pts, &out]));
    let (got, want) = (
        std::fs::read(&out).unwrap(),
        std::fs::read(&expected).unwrap(),
    );
    assert_eq!(got.len(), want.len(), "answer layouts differ");
    if let Some(i) = (0..got.len()).find(|&i| got[i] != want[i]) {
        panic!(
            "C++ field answer differs from Rust's at byte {i} of {}",
            want.len()
        );
    }
    // A snapshot without a field: a clear error, not a crash.
    let bad = Command::new(build.join("field"))
        .args([&f.snapshot, &pts, &out])
        .output()
        .unwrap();
    assert!(!bad.status.success());
    assert!(
        String::from_utf8_lossy(&bad.stderr).contains("no distance field"),
        "{bad:?}"
    );
    if let Some(py) = python_api() {
        let said = run_ok(
            Command::new(py)
                .args(["-m", "pytest", "-q", "-rs", "-p", "no:cacheprovider"])
                .arg(format!("{REPO}/python/tests/test_field.py"))
                .env("VOXMAP_FIXTURE", &f.dir),
        );
        assert!(
            said.contains(" passed") && !said.contains("skipped"),
            "{said}"
        );
    }
    std::fs::remove_dir_all(&f.dir).unwrap();
}

#[test]
fn python_answers_as_the_rust_view() {
    let Some(py) = python_api() else { return };
    let f = fixture("py_api");
    let out = run_ok(
        Command::new(py)
            .args(["-m", "pytest", "-q", "-rs", "-p", "no:cacheprovider"])
            .arg(format!("{REPO}/python/tests/test_view.py"))
            .env("VOXMAP_FIXTURE", &f.dir),
    );
    assert!(out.contains(" passed") && !out.contains("skipped"), "{out}");
    std::fs::remove_dir_all(&f.dir).unwrap();
}

/// Wait until a snapshot holds frame `seq`.
fn wait_for_seq(sub: &mut SnapshotSubscriber, seq: u64) {
    let deadline = Instant::now() + Duration::from_secs(30);
    while Instant::now() < deadline {
        sub.wait_for_update(Duration::from_millis(200)).unwrap();
        if sub.latest().unwrap().is_some_and(|v| v.sequence() >= seq) {
            return;
        }
    }
    panic!("no snapshot with frame {seq}");
}

#[test]
fn frames_from_cpp_and_python_come_back_to_cpp_and_python() {
    let (Some(prefix), Some(py)) = (c_prefix(), python_api()) else {
        return;
    };
    let dir = tmpdir("live");
    let build = dir.join("examples");
    cmake_build("examples/cpp", &prefix, &build);
    let programs = dir.join("programs");
    cmake_build("c/tests/programs", &prefix, &programs);
    let name = unique_prefix("live");
    let svc = Service::start(&name, &["--resolution", "0.1"]);
    let mut sub = {
        let deadline = Instant::now() + Duration::from_secs(20);
        loop {
            match SnapshotSubscriber::connect(&name, "default") {
                Ok(s) => break s,
                Err(e) if Instant::now() > deadline => panic!("connect: {e}"),
                Err(_) => std::thread::sleep(Duration::from_millis(50)),
            }
        }
    };
    wait_for_seq(&mut sub, 0);
    // C++: a wall 2 m ahead on +x (frame 1 of its publisher).
    let out = run_ok(Command::new(build.join("driver")).args([&name, "default", "2.0"]));
    assert!(out.contains("sent frame 1: 3072 points"), "{out}");
    // Python: a wall 2 m away on +y, then the checks of both walls from Python.
    let out = run_ok(
        Command::new(&py)
            .args(["-m", "pytest", "-q", "-rs", "-p", "no:cacheprovider"])
            .arg(format!("{REPO}/python/tests/test_live.py"))
            .env("VOXMAP_LIVE_PREFIX", &name),
    );
    assert!(
        out.contains("1 passed") && !out.contains("skipped"),
        "{out}"
    );
    // C++ reads both: the path along +x and the one along +y are blocked at the walls, the
    // one along -x is clear.
    let out = run_ok(Command::new(build.join("planner")).args([
        name.as_str(),
        "default",
        "0,0,0",
        "3,0,0",
        "0,0,0",
        "0,3,0",
        "0,0,0",
        "-1,0,0",
    ]));
    let line = |k: &str| {
        out.lines()
            .find(|l| l.starts_with(k))
            .unwrap_or_else(|| panic!("no {k:?} in {out}"))
            .to_string()
    };
    assert!(line("segment 0:").contains("blocked at 2.050,"), "{out}");
    assert!(
        line("segment 2:").contains("blocked at 0.050,2.050,"),
        "{out}"
    );
    assert!(line("segment 4:").ends_with("clear"), "{out}");
    assert!(line("waypoint 0:").ends_with("free"), "{out}");
    // C: the publisher's refusals and the control requests (save, clear, load).
    let out = run_ok(Command::new(programs.join("c_checks")).args([
        "live",
        name.as_str(),
        dir.to_str().unwrap(),
    ]));
    assert!(out.contains("ok live"), "{out}");
    drop(svc);
    std::fs::remove_dir_all(&dir).unwrap();
}

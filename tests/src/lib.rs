//! Helpers for the cross-process tests: find (or build) the `voxmap` binary and run a
//! service under a unique prefix that is stopped when the handle drops.

use std::path::PathBuf;
use std::process::{Child, Command, Stdio};

/// What `cargo` builds for a test that needs the `voxmap` binary: the workspace's
/// binaries with its test targets, so that the features are those `cargo test --workspace`
/// unifies (its dev-dependencies' included) and cargo reuses that build for all but the
/// binary's own crate. Built on its own (`-p voxmap-service`), nearly every crate was
/// built again with other features: over 2 minutes of CI. (Not `--lib`: that would build
/// the Python extension, which `cargo test` does not.)
const WORKSPACE_BUILD: [&str; 4] = ["build", "--workspace", "--bins", "--tests"];

/// Path of the `voxmap` binary of this build profile, brought up to date once per test
/// process (`cargo test` does not build other packages' binaries) by [`WORKSPACE_BUILD`].
pub fn voxmap_bin() -> PathBuf {
    static BUILT: std::sync::Once = std::sync::Once::new();
    let exe = std::env::current_exe().expect("test exe");
    let profile_dir = exe
        .parent()
        .and_then(|d| d.parent())
        .expect("target/<profile>")
        .to_path_buf();
    let bin = profile_dir.join("voxmap");
    BUILT.call_once(|| {
        let release = profile_dir.file_name().is_some_and(|n| n == "release");
        let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
        let mut c = Command::new(cargo);
        c.args(WORKSPACE_BUILD);
        if release {
            c.arg("--release");
        }
        assert!(
            c.status().expect("cargo build").success(),
            "building voxmap failed"
        );
    });
    bin
}

/// A unique service prefix per test and process.
pub fn unique_prefix(test: &str) -> String {
    let t = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .unwrap()
        .as_nanos();
    format!("vxt{}_{test}_{}", std::process::id(), t % 1_000_000_007)
}

/// A running `voxmap serve`, killed on drop if still running.
pub struct Service {
    pub child: Child,
    pub prefix: String,
    /// Reads the service's stderr as it is written: a pipe nobody reads fills at 64 KiB
    /// and then blocks the service in its next log line (a long run looked like a stall).
    log: Option<std::thread::JoinHandle<String>>,
}

impl Service {
    /// `voxmap serve --prefix PREFIX --threads 2 --exit-after 120`, then `extra`.
    pub fn start(prefix: &str, extra: &[&str]) -> Self {
        let args = [&["--threads", "2", "--exit-after", "120"][..], extra].concat();
        Self::spawn(prefix, &args, &[])
    }

    /// `voxmap serve --prefix PREFIX` with exactly `args`, in the environment `env` adds to.
    pub fn spawn(prefix: &str, args: &[&str], env: &[(&str, &str)]) -> Self {
        let mut child = Command::new(voxmap_bin())
            .args(["serve", "--prefix", prefix])
            .args(args)
            .envs(env.iter().copied())
            .stdout(Stdio::null())
            .stderr(Stdio::piped())
            .spawn()
            .expect("spawn voxmap serve");
        let mut err = child.stderr.take().expect("piped stderr");
        let log = std::thread::spawn(move || {
            use std::io::Read;
            let mut log = String::new();
            let _ = err.read_to_string(&mut log);
            log
        });
        Service {
            child,
            prefix: prefix.to_string(),
            log: Some(log),
        }
    }

    /// Send a signal (by name, e.g. "TERM", "KILL") and wait for exit; returns the status
    /// and everything the service wrote to stderr.
    pub fn signal_and_wait(mut self, sig: &str) -> (std::process::ExitStatus, String) {
        Command::new("kill")
            .args([&format!("-{sig}"), &self.child.id().to_string()])
            .status()
            .expect("kill");
        let st = self.child.wait().expect("wait");
        let err = self.log.take().map(|l| l.join().unwrap_or_default());
        (st, err.unwrap_or_default())
    }
}

impl Drop for Service {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// Points of a closed box room (half extents `h`) seen from `sensor`, in the sensor
/// frame (identity orientation), one per Fibonacci-sphere direction.
pub fn room_scan(h: [f64; 3], sensor: [f64; 3], n: usize) -> Vec<[f32; 3]> {
    (0..n)
        .map(|i| {
            let z = 1.0 - 2.0 * (i as f64 + 0.5) / n as f64;
            let r = (1.0 - z * z).sqrt();
            let phi = i as f64 * 2.399963229728653;
            let d = [r * phi.cos(), r * phi.sin(), z];
            let t = (0..3)
                .map(|a| {
                    if d[a] > 0.0 {
                        (h[a] - 0.01 - sensor[a]) / d[a]
                    } else if d[a] < 0.0 {
                        (-h[a] + 0.01 - sensor[a]) / d[a]
                    } else {
                        f64::INFINITY
                    }
                })
                .fold(f64::INFINITY, f64::min);
            [0, 1, 2].map(|a| (d[a] * t) as f32)
        })
        .collect()
}

/// The shared real data folder of the TUM RGB-D frames (`../shared` beside the repo).
pub fn tum_dir() -> PathBuf {
    let d = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../../shared/data/real/tum_fr2_pioneer_slam2");
    assert!(
        d.is_dir(),
        "{} missing: ../shared must sit beside the repo",
        d.display()
    );
    d
}

/// One TUM depth frame, back-projected.
pub struct TumFrame {
    /// The time stamp as the file name spells it (seconds, six decimals).
    pub stamp: String,
    /// `tx ty tz qx qy qz qw` of the camera's optical frame in the world, as TUM gives it.
    pub pose: String,
    /// Points in the optical frame (x right, y down, z forward).
    pub points: Vec<[f32; 3]>,
}

/// The ten TUM freiburg2_pioneer_slam2 depth frames, every `step`-th pixel in each
/// direction, with their poses from the association file.
pub fn tum_frames(step: usize) -> Vec<TumFrame> {
    let data = tum_dir();
    let assoc = std::fs::read_to_string(data.join("my_association.txt")).expect("association file");
    let mut poses = std::collections::HashMap::new();
    for l in assoc.lines().filter(|l| !l.starts_with('#')) {
        let w: Vec<&str> = l.split_whitespace().collect();
        if w.len() == 9 {
            let t = w[1].trim_start_matches("depth/").trim_end_matches(".png");
            poses.insert(t.to_string(), w[2..9].join(" "));
        }
    }
    let mut names: Vec<String> = std::fs::read_dir(data.join("depth"))
        .expect("depth/")
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    names.sort();
    names
        .iter()
        .map(|n| {
            let dec = png::Decoder::new(std::io::BufReader::new(
                std::fs::File::open(data.join("depth").join(n)).unwrap(),
            ));
            let mut r = dec.read_info().unwrap();
            let mut buf = vec![0; r.output_buffer_size().unwrap()];
            let info = r.next_frame(&mut buf).unwrap();
            assert_eq!(
                (info.width, info.height, info.bit_depth),
                (640, 480, png::BitDepth::Sixteen)
            );
            // TUM's back-projection: 5000 units per metre, fx = fy = 525, cx 319.5, cy 239.5.
            let mut points = Vec::new();
            for v in (0..480).step_by(step) {
                for u in (0..640).step_by(step) {
                    let d =
                        u16::from_be_bytes([buf[2 * (v * 640 + u)], buf[2 * (v * 640 + u) + 1]]);
                    if d == 0 {
                        continue;
                    }
                    let z = d as f64 / 5000.0;
                    points.push([
                        ((u as f64 - 319.5) * z / 525.0) as f32,
                        ((v as f64 - 239.5) * z / 525.0) as f32,
                        z as f32,
                    ]);
                }
            }
            let stamp = n.trim_end_matches(".png").to_string();
            TumFrame {
                pose: poses
                    .get(&stamp)
                    .unwrap_or_else(|| panic!("no pose for {stamp}"))
                    .clone(),
                stamp,
                points,
            }
        })
        .collect()
}

/// The TUM frames (every `step`-th pixel) in `dir/frames`: KITTI `.bin` scans named by
/// stamp (float32 x y z intensity) and `poses.txt` in TUM's format, for `make_bags.py tum`
/// and for replay with the poses given directly.
pub fn write_tum_frames(dir: &std::path::Path, step: usize) -> PathBuf {
    let frames_dir = dir.join("frames");
    std::fs::create_dir_all(&frames_dir).unwrap();
    let mut poses = String::new();
    for f in tum_frames(step) {
        let bin: Vec<u8> = f
            .points
            .iter()
            .flat_map(|p| [p[0], p[1], p[2], 0.0])
            .flat_map(f32::to_le_bytes)
            .collect();
        std::fs::write(frames_dir.join(format!("{}.bin", f.stamp)), bin).unwrap();
        poses.push_str(&format!("{} {}\n", f.stamp, f.pose));
    }
    std::fs::write(frames_dir.join("poses.txt"), &poses).unwrap();
    frames_dir
}

/// A Python with the `rosbags` package: `$VOXMAP_PYTHON`, else `python3` if it has it.
/// `None` (with a notice) when there is none, unless VOXMAP_REQUIRE_ROSBAGS is set, as CI
/// does, which makes that a failure.
pub fn python_with_rosbags() -> Option<PathBuf> {
    python_with(
        "rosbags, mcap, numpy",
        "VOXMAP_REQUIRE_ROSBAGS",
        "pip install rosbags mcap numpy",
        "the ROS 2 bag tests",
    )
}

/// `$VOXMAP_PYTHON` (else `python3`) if it imports `modules`; `None` with a notice that
/// `skipping` is skipped, unless the variable `require` is set (as CI does), which makes a
/// missing module a failure that says to run `install`.
pub fn python_with(modules: &str, require: &str, install: &str, skipping: &str) -> Option<PathBuf> {
    let py =
        std::env::var_os("VOXMAP_PYTHON").map_or_else(|| PathBuf::from("python3"), PathBuf::from);
    let has = Command::new(&py)
        .args(["-c", &format!("import {modules}")])
        .stderr(Stdio::null())
        .status()
        .is_ok_and(|s| s.success());
    if has {
        return Some(py);
    }
    assert!(
        std::env::var_os(require).is_none(),
        "{} cannot import {modules} ({install})",
        py.display()
    );
    eprintln!("NOTICE: no Python with {modules}; skipping {skipping}");
    None
}

/// Run one of OctoMap's programs; `None` when octomap-tools is not installed (CI installs
/// it and sets VOXMAP_REQUIRE_OCTOMAP=1, which turns absence into a failure).
pub fn octomap_tool(args: &[&str]) -> Option<String> {
    match Command::new(args[0]).args(&args[1..]).output() {
        Ok(o) => {
            assert!(
                o.status.success(),
                "{args:?}: {}",
                String::from_utf8_lossy(&o.stderr)
            );
            Some(format!(
                "{}{}",
                String::from_utf8_lossy(&o.stdout),
                String::from_utf8_lossy(&o.stderr)
            ))
        }
        Err(e) => {
            assert!(
                std::env::var_os("VOXMAP_REQUIRE_OCTOMAP").is_none(),
                "{}: {e} (install Debian's octomap-tools)",
                args[0]
            );
            eprintln!("octomap-tools not installed; skipping the OctoMap read-back");
            None
        }
    }
}

/// The integer after `key` in `text`.
pub fn number_after(text: &str, key: &str) -> u64 {
    let at = text
        .find(key)
        .unwrap_or_else(|| panic!("'{key}' not in:\n{text}"))
        + key.len();
    text[at..]
        .trim_start()
        .split(|c: char| !c.is_ascii_digit())
        .next()
        .unwrap()
        .parse()
        .unwrap()
}

/// Call `f` until it succeeds (a service just started may not have its ports yet), for
/// at most 20 s.
pub fn connect_with_retry<T>(f: impl Fn() -> Result<T, voxmap_client::ClientError>) -> T {
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(20);
    loop {
        match f() {
            Ok(t) => return t,
            Err(e) if std::time::Instant::now() > deadline => panic!("connect: {e}"),
            Err(_) => std::thread::sleep(std::time::Duration::from_millis(50)),
        }
    }
}

/// A small deterministic generator (an LCG) for test inputs: the same sequence everywhere.
pub struct TestRng(pub u64);

impl TestRng {
    pub fn next_u64(&mut self) -> u64 {
        self.0 = self
            .0
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        self.0
    }

    /// Uniform in [0, 1).
    pub fn f(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64
    }

    /// Uniform in [0, n) (from the high bits: an LCG's low bits are poor).
    pub fn below(&mut self, n: u64) -> u64 {
        ((u128::from(self.next_u64()) * u128::from(n)) >> 64) as u64
    }
}

/// A fresh directory under the system's temp dir, unique to this test and process.
pub fn tmpdir(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(unique_prefix(name));
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// Run the `voxmap` binary.
pub fn voxmap(args: &[&str]) -> std::process::Output {
    Command::new(voxmap_bin())
        .args(args)
        .output()
        .expect("run voxmap")
}

/// Run the `voxmap` binary, which must succeed; its standard output.
pub fn ok(args: &[&str]) -> String {
    run_ok(Command::new(voxmap_bin()).args(args))
}

/// Run a program, which must succeed; its standard output.
pub fn run_ok(cmd: &mut Command) -> String {
    let out = cmd.output().expect("spawn");
    assert!(
        out.status.success(),
        "{cmd:?} failed: {}\n{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8_lossy(&out.stdout).into_owned()
}

/// Every known voxel of a map with its stored value, sorted.
pub fn voxels(map: &voxmap_map::OccupancyMap) -> Vec<([i32; 3], i8)> {
    let mut v: Vec<_> = map
        .grid()
        .active_voxels()
        .map(|(c, x)| (c.to_array(), x))
        .collect();
    v.sort();
    v
}

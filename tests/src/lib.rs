//! Helpers for the cross-process tests: find (or build) the `voxmap` binary and run a
//! service under a unique prefix that is stopped when the handle drops.

use std::path::PathBuf;
use std::process::{Child, Command, Stdio};

/// Path of the `voxmap` binary of this build profile, brought up to date once per test
/// process (`cargo test` does not build other packages' binaries).
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
        c.args(["build", "-p", "voxmap-service", "--bin", "voxmap"]);
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
}

impl Service {
    pub fn start(prefix: &str, extra: &[&str]) -> Self {
        let child = Command::new(voxmap_bin())
            .args([
                "serve",
                "--prefix",
                prefix,
                "--threads",
                "2",
                "--exit-after",
                "120",
            ])
            .args(extra)
            .stdout(Stdio::null())
            .stderr(Stdio::piped())
            .spawn()
            .expect("spawn voxmap serve");
        Service {
            child,
            prefix: prefix.to_string(),
        }
    }

    /// Send a signal (by name, e.g. "TERM", "KILL") and wait for exit; returns the status
    /// and everything the service wrote to stderr.
    pub fn signal_and_wait(mut self, sig: &str) -> (std::process::ExitStatus, String) {
        Command::new("kill")
            .args([&format!("-{sig}"), &self.child.id().to_string()])
            .status()
            .expect("kill");
        let mut err = String::new();
        if let Some(mut e) = self.child.stderr.take() {
            use std::io::Read;
            let _ = e.read_to_string(&mut err);
        }
        let st = self.child.wait().expect("wait");
        (st, err)
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

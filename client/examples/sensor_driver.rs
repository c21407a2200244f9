//! A simulated sensor driver: publishes scans of a box room to a running service.
//!
//! terminal 1: cargo run --release -p voxmap-service -- serve
//! terminal 2: cargo run --release -p voxmap-client --example sensor_driver
//! terminal 3: cargo run --release -p voxmap-client --example planner

use voxmap_client::{FramePublisher, Isometry3};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut publisher = FramePublisher::connect("voxmap", "default")?;
    let (h, n) = ([4.0f64, 3.0, 1.5], 30_000usize);
    for k in 0..50u64 {
        // The sensor moves along x; points are in the sensor frame.
        let s = [-2.0 + 0.08 * k as f64, 0.0, 0.0];
        let mut frame = publisher.loan(n)?;
        for (i, p) in frame.points_mut().iter_mut().enumerate() {
            let z = 1.0 - 2.0 * (i as f64 + 0.5) / n as f64;
            let r = (1.0 - z * z).sqrt();
            let phi = i as f64 * 2.399963229728653;
            let d = [r * phi.cos(), r * phi.sin(), z];
            let t = (0..3)
                .filter(|&a| d[a] != 0.0)
                .map(|a| ((if d[a] > 0.0 { h[a] } else { -h[a] }) - s[a]) / d[a])
                .fold(f64::INFINITY, f64::min);
            *p = [(d[0] * t) as f32, (d[1] * t) as f32, (d[2] * t) as f32];
        }
        let seq = frame.send(&Isometry3::translation(s[0], s[1], s[2]), k * 100_000_000)?;
        println!("sent frame {seq}");
        std::thread::sleep(std::time::Duration::from_millis(100));
    }
    Ok(())
}

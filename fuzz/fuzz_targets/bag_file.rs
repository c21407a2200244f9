//! Arbitrary bytes as a `.mcap` and as a `.db3` bag file: opened and read through; must
//! never panic.
#![no_main]

use libfuzzer_sys::fuzz_target;
use std::ops::ControlFlow;
use voxmap_ros::bag::Bag;

fuzz_target!(|data: &[u8]| {
    let dir = std::env::temp_dir();
    for ext in ["mcap", "db3"] {
        let path = dir.join(format!("voxmap_fuzz_{}.{ext}", std::process::id()));
        if std::fs::write(&path, data).is_err() {
            return;
        }
        if let Ok(bag) = Bag::open(&path) {
            for i in 0..bag.files.len() {
                let _ = bag.read_file(i, &|_| true, &mut |m| {
                    let _ = voxmap_ros::msg::decode::<voxmap_ros::msg::PointCloud2<&[u8]>>(m.data);
                    ControlFlow::Continue(())
                });
            }
        }
        let _ = std::fs::remove_file(&path);
    }
});

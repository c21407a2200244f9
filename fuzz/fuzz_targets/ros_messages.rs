//! Arbitrary bytes as each message voxmap reads (PointCloud2, TFMessage, Odometry,
//! PoseStamped), decoded, and fed through the message filter as TF and as clouds: must
//! never panic.
#![no_main]

use libfuzzer_sys::fuzz_target;
use voxmap_ros::msg::{self, types};
use voxmap_ros::sync::{CloudSync, PoseSource, SyncConfig};

fuzz_target!(|data: &[u8]| {
    if let Ok(c) = msg::decode::<msg::PointCloud2<&[u8]>>(data) {
        if let Ok(r) = voxmap_ros::cloud::points(&c) {
            assert!(r.points.len() as u64 + r.non_finite <= u64::from(c.width) * u64::from(c.height));
        }
    }
    let _ = msg::decode::<msg::TfMessage>(data);
    let mut sync = CloudSync::new(SyncConfig {
        poses: PoseSource::Topic {
            topic: "/odom".into(),
            pose_frame: Some("base".into()),
        },
        ..SyncConfig::default()
    });
    let _ = sync.tf_message(1, data, true);
    let _ = sync.tf_message(2, data, false);
    let _ = sync.pose_message(3, types::ODOMETRY, data);
    let _ = sync.pose_message(4, types::POSE_STAMPED, data);
    let _ = sync.cloud("/c", 0, 5, data);
    let _ = sync.ready();
    let _ = sync.finish();
});

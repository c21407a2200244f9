//! A planner: waits for snapshots and queries them in place (no copy).
//!
//! Run beside `voxmap serve` and the `sensor_driver` example (see its header).

use std::time::Duration;
use voxmap_client::{SnapshotSubscriber, VoxelState, WorldPoint};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut sub = SnapshotSubscriber::connect("voxmap", "default")?;
    for _ in 0..100 {
        if !sub.wait_for_update(Duration::from_secs(1))? {
            continue;
        }
        let Some(view) = sub.latest()? else { continue };
        let (known, occupied) = view.counts();
        let here = WorldPoint::new(0.0, 0.0, 0.0);
        let goal = WorldPoint::new(3.0, 1.0, 0.0);
        let los = view.first_hit(&here, &goal, true)?;
        // A candidate trajectory's samples, checked in one batched call (faster per
        // point than one `state_at` each on a big map).
        let samples: Vec<WorldPoint> = (0..200)
            .map(|i| {
                let t = f64::from(i) * 0.05;
                WorldPoint::new(t.cos() * 2.0, t.sin() * 2.0, 0.2 * t)
            })
            .collect();
        let mut states = Vec::with_capacity(samples.len());
        view.states_at(&samples, &mut states);
        let colliding = states
            .iter()
            .filter(|&&s| s == VoxelState::Occupied)
            .count();
        let box_free = view.is_box_free(
            &WorldPoint::new(-0.3, -0.3, -0.3),
            &WorldPoint::new(0.3, 0.3, 0.3),
            false,
        )?;
        println!(
            "snapshot {}: {known} known, {occupied} occupied; origin {:?}; line of sight to goal {}; robot box free: {box_free}; trajectory samples in occupied voxels: {colliding}",
            view.sequence(),
            view.state_at(&here),
            match los {
                None => "clear".to_string(),
                Some(v) => format!("blocked at voxel {v:?}"),
            }
        );
    }
    Ok(())
}

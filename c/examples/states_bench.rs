//! The Rust side of `bench/bindings_vs_rust.sh`: ns per point of `SnapshotView::states_at`
//! on a snapshot file, over the points of a file (f64 x, y, z after one another), in
//! batches, median of the repetitions. `bench/states_bench.cpp` and `states_bench.py` time
//! the C and Python calls on the same files.
//!
//!   cargo run --release -p voxmap-c --example states_bench -- SNAPSHOT POINTS BATCH REPS

use std::time::Instant;
use voxmap_reader::mapfile;
use voxmap_reader::snapshot::SnapshotView;
use voxmap_reader::{VoxelState, WorldPoint};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let [snap, points, batch, reps] = args.as_slice() else {
        return Err("usage: states_bench SNAPSHOT POINTS BATCH REPS".into());
    };
    let (batch, reps): (usize, usize) = (batch.parse()?, reps.parse()?);
    let bytes = mapfile::read_as_snapshot(snap.as_ref())?;
    let view = SnapshotView::open(&bytes)?;
    let raw = std::fs::read(points)?;
    let xyz: Vec<f64> = raw
        .chunks_exact(8)
        .map(|b| f64::from_le_bytes(b.try_into().unwrap_or([0; 8])))
        .collect();
    let pts: Vec<WorldPoint> = xyz
        .chunks_exact(3)
        .map(|c| WorldPoint::new(c[0], c[1], c[2]))
        .collect();
    let time = |f: &mut dyn FnMut() -> usize| {
        let mut per_point = Vec::with_capacity(reps);
        let mut occupied = 0;
        for _ in 0..reps {
            let t = Instant::now();
            occupied += f();
            per_point.push(t.elapsed().as_secs_f64() * 1e9 / pts.len() as f64);
        }
        per_point.sort_by(f64::total_cmp);
        (per_point[reps / 2], occupied)
    };
    let mut out = Vec::with_capacity(batch);
    let (ns, occupied) = time(&mut || {
        let mut n = 0;
        for chunk in pts.chunks(batch) {
            out.clear();
            view.states_at(chunk, &mut out);
            n += out.iter().filter(|s| **s == VoxelState::Occupied).count();
        }
        n
    });
    let what = format!("median of {reps}, batch {batch}, {} points", pts.len());
    println!("rust states_at: {ns:.1} ns/point ({what}; {occupied} occupied answers)");
    // What the C and Python calls run, in this process: it tells the binding's own cost
    // from the code layout of another binary.
    let mut codes = vec![0u8; batch];
    let (ns, occupied) = time(&mut || {
        let mut n = 0;
        for chunk in xyz.chunks(3 * batch) {
            view.state_codes_at(chunk, &mut codes);
            n += codes[..chunk.len() / 3].iter().filter(|&&c| c == 2).count();
        }
        n
    });
    println!("rust state_codes_at: {ns:.1} ns/point ({what}; {occupied} occupied answers)");
    Ok(())
}

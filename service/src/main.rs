//! `voxmap`: the mapping service and its tools.

mod bags;
mod bench;
mod config;
mod demo;
mod distance;
mod filejobs;
mod files;
mod os;
mod quantile;
mod render;
mod replay;
mod rng;
mod serve;
mod sim;
mod simproc;
mod tum;

use clap::{Parser, Subcommand};

#[derive(Parser)]
#[command(
    name = "voxmap",
    version,
    about = "Sparse 3D occupancy mapping over shared memory"
)]
struct Cli {
    #[command(subcommand)]
    cmd: Cmd,
}

#[derive(Subcommand)]
enum Cmd {
    /// Run the whole system for a while with a simulated sensor and planner; write pictures.
    Demo(demo::DemoArgs),
    /// Run the mapping service: frames in, snapshots out, over iceoryx2.
    Serve(serve::ServeArgs),
    /// Feed recorded scans to a running service, or offline into a map file.
    Replay(replay::ReplayArgs),
    /// Export a map or snapshot file to OctoMap .bt, PLY and/or a snapshot file.
    Export(files::ExportArgs),
    /// Draw a map, snapshot or .bt file as a PNG (top-down or a slice).
    Render(render::RenderArgs),
    /// Show what a map, snapshot or .bt file holds, or why it is invalid.
    Inspect(files::InspectArgs),
    /// The distance field of a map or snapshot file at points: `x y z distance gx gy gz`.
    Distance(distance::DistanceArgs),
    /// Print the embedded default configuration (a starting point for --config).
    Config,
    /// Time frame integration on the paper's synthetic workloads.
    Bench(bench::BenchArgs),
    /// The demo's simulated LiDAR (a separate process).
    #[command(hide = true)]
    SimSensor(simproc::SimArgs),
    /// The demo's planner (a separate process).
    #[command(hide = true)]
    SimPlanner(simproc::SimArgs),
}

/// Errors are reported as one line, the error and its causes (`a: b: c`), with a non-zero
/// exit; never with a backtrace, whatever `RUST_BACKTRACE` says: they are expected
/// failures (a bad file, a full disk), not bugs.
fn main() -> std::process::ExitCode {
    os::keep_freed_memory();
    match run(Cli::parse().cmd) {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("voxmap: error: {e:#}");
            std::process::ExitCode::FAILURE
        }
    }
}

fn run(cmd: Cmd) -> anyhow::Result<()> {
    match cmd {
        Cmd::Demo(a) => demo::run(a),
        Cmd::Serve(a) => serve::run(a),
        Cmd::Replay(a) => replay::run(a),
        Cmd::Export(a) => files::export(a),
        Cmd::Render(a) => render::run(a),
        Cmd::Inspect(a) => files::inspect(a),
        Cmd::Distance(a) => distance::run(a),
        Cmd::Config => {
            print!("{}", config::DEFAULT_TOML);
            Ok(())
        }
        Cmd::Bench(a) => bench::run(a),
        Cmd::SimSensor(a) => simproc::sensor(a),
        Cmd::SimPlanner(a) => simproc::planner(a),
    }
}

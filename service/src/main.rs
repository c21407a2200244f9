//! `voxmap`: the mapping service and its tools.

mod bench;
mod serve;

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
    /// Run the mapping service: frames in, snapshots out, over iceoryx2.
    Serve(serve::ServeArgs),
    /// Time frame integration on the paper's synthetic workloads.
    Bench(bench::BenchArgs),
}

fn main() -> anyhow::Result<()> {
    match Cli::parse().cmd {
        Cmd::Bench(a) => bench::run(a),
        Cmd::Serve(a) => serve::run(a),
    }
}

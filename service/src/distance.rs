//! `voxmap distance`: the distance field of a map or snapshot file at given points, one
//! line in, one line out.

use anyhow::{bail, Context, Result};
use clap::Args;
use std::io::{BufRead, Write};
use std::path::PathBuf;
use voxmap_map::field::{FieldConfig, UnknownPolicy};
use voxmap_map::io::mapfile;
use voxmap_map::snapshot::{Nearest, SnapshotView};
use voxmap_map::WorldPoint;

#[derive(Args, Debug)]
pub struct DistanceArgs {
    /// Map file (the field is built from it), or snapshot file that carries a field.
    pub file: PathBuf,
    /// Points, one `x y z` line each (metres); `-` reads standard input.
    #[arg(long)]
    pub points: PathBuf,
    /// For a map file: distances kept below this (metres).
    #[arg(long, default_value_t = 2.0)]
    pub max_distance: f64,
    /// For a map file: what unknown voxels count as, free or occupied.
    #[arg(long, default_value = "free")]
    pub unknown: UnknownPolicy,
    /// Also print the nearest obstacle voxel's centre (`ox oy oz`, nan when none).
    #[arg(long)]
    pub nearest: bool,
    /// The distance of the voxel holding each point (centre to centre, as dynamicEDT3D
    /// answers), not interpolated: prints `x y z distance` only.
    #[arg(long)]
    pub voxel: bool,
}

/// Prints `x y z distance gx gy gz` per point: the distance interpolated between voxel
/// centres and its gradient; `-1 0 0 0` where no obstacle lies within the max distance,
/// `nan nan nan nan` where the field does not reach (unknown space, outside the window).
pub fn run(a: DistanceArgs) -> Result<()> {
    let cfg = FieldConfig {
        max_distance: a.max_distance,
        unknown: a.unknown,
        window: None,
    };
    let bytes = mapfile::read_as_snapshot_with_field(&a.file, &cfg)?;
    let view = SnapshotView::open(&bytes)?;
    let Some(field) = view.distance_field() else {
        bail!(
            "{}: a snapshot without a distance field (give the map file, or a snapshot of a service run with --esdf)",
            a.file.display()
        );
    };
    let input: Box<dyn BufRead> = if a.points.as_os_str() == "-" {
        Box::new(std::io::stdin().lock())
    } else {
        let f = std::fs::File::open(&a.points)
            .with_context(|| format!("reading {}", a.points.display()))?;
        Box::new(std::io::BufReader::new(f))
    };
    let out = std::io::stdout();
    let mut out = std::io::BufWriter::new(out.lock());
    for (i, line) in input.lines().enumerate() {
        let line = line.with_context(|| format!("reading {}", a.points.display()))?;
        let t = line.trim();
        if t.is_empty() || t.starts_with('#') {
            continue;
        }
        let v: Vec<f64> = t
            .split(|c: char| c.is_whitespace() || c == ',')
            .filter(|w| !w.is_empty())
            .map(|w| w.parse::<f64>())
            .collect::<Result<_, _>>()
            .ok()
            .filter(|v: &Vec<f64>| v.len() == 3)
            .with_context(|| {
                format!("{} line {}: not `x y z`: {t:?}", a.points.display(), i + 1)
            })?;
        let p = WorldPoint::new(v[0], v[1], v[2]);
        let d = if a.voxel {
            match view
                .transform()
                .voxel_of(&p)
                .and_then(|v| field.distance(v))
            {
                None => "nan".to_string(),
                Some(d) if d >= field.max_distance() => "-1".to_string(),
                Some(d) => format!("{d:.6}"),
            }
        } else {
            match field.distance_and_gradient_at(&p) {
                None => "nan nan nan nan".to_string(),
                Some((d, _)) if d >= field.max_distance() => "-1 0 0 0".to_string(),
                Some((d, g)) => format!("{d:.6} {:.6} {:.6} {:.6}", g.x, g.y, g.z),
            }
        };
        write!(out, "{} {} {} {d}", v[0], v[1], v[2])?;
        if a.nearest {
            match field.nearest_obstacle(&p) {
                Nearest::At { centre, .. } => {
                    write!(out, " {:.6} {:.6} {:.6}", centre.x, centre.y, centre.z)?
                }
                _ => write!(out, " nan nan nan")?,
            }
        }
        writeln!(out)?;
    }
    out.flush()?;
    Ok(())
}

//! Reading any voxmap-readable map file (map file, snapshot file, OctoMap `.bt`), and the
//! `inspect` and `export` subcommands built on it.

use anyhow::{bail, Context, Result};
use clap::Args;
use std::path::{Path, PathBuf};
use voxmap_map::grid::voxel_at;
use voxmap_map::io::{mapfile, octomap, ply};
use voxmap_map::snapshot::{SnapshotView, MAGIC as SNAPSHOT_MAGIC};
use voxmap_map::LeafOccupancy;

/// Most known voxels a `.bt` file may expand to: 2^28, more than a 60 m LiDAR map holds
/// (2.2e8), and at most 2^19 leaves (about 80 MB decoded).
const MAX_BT_VOXELS: u64 = 1 << 28;
/// Most occupied voxels a PLY export writes: 2^26 points, a 1.5 GB file.
const MAX_PLY_POINTS: u64 = 1 << 26;

/// A file's occupancy and what it says about itself.
pub struct Loaded {
    pub resolution: f64,
    pub leaves: Vec<LeafOccupancy>,
    /// (name, value) lines for `inspect`.
    pub details: Vec<(&'static str, String)>,
}

impl Loaded {
    /// Read and validate a map, snapshot or `.bt` file, told apart by their first bytes.
    pub fn read(path: &Path) -> Result<Self> {
        let bytes = std::fs::read(path).with_context(|| format!("reading {}", path.display()))?;
        let name = path.display();
        let mut d: Vec<(&'static str, String)> = Vec::new();
        if bytes.starts_with(&mapfile::MAP_MAGIC) {
            let (map, field) = mapfile::decode_map_with_field(&bytes).map_err(|e| match e {
                mapfile::Decode::Version(v) => anyhow::anyhow!(
                    "{name}: map file version {v} is not supported (this build reads {})",
                    mapfile::MAP_VERSION
                ),
                mapfile::Decode::Corrupt(why) => anyhow::anyhow!("{name}: corrupt map file: {why}"),
            })?;
            let c = map.counts();
            let m = map.model();
            d.push((
                "format",
                format!(
                    "voxmap map file, version {}",
                    u32::from_le_bytes(bytes[8..12].try_into().unwrap_or_default())
                ),
            ));
            d.push(("resolution", format!("{} m", map.resolution())));
            d.push((
                "sensor model",
                format!(
                    "p_hit {} p_miss {} clamp {}..{} threshold {}",
                    m.p_hit, m.p_miss, m.clamp_min, m.clamp_max, m.occupancy_threshold
                ),
            ));
            d.push(("leaves", c.leaves.to_string()));
            d.push(("occupied voxels", c.occupied.to_string()));
            d.push(("free voxels", c.free.to_string()));
            d.push((
                "memory when loaded",
                format!("{} bytes", map.memory_bytes()),
            ));
            d.push((
                "distance field",
                match &field {
                    None => "none".into(),
                    Some(f) => format!(
                        "to {} m, unknown {}, {} voxels in the band{}",
                        f.max_distance(),
                        f.config().unknown.name(),
                        f.band_voxels(),
                        f.window().map_or(String::new(), |(lo, hi)| format!(
                            ", window {:?}..{:?}",
                            lo.to_array(),
                            hi.to_array()
                        ))
                    ),
                },
            ));
            let leaves: Vec<_> = map.leaf_occupancy().collect();
            push_bounds(&mut d, &leaves, map.resolution());
            return Ok(Self {
                resolution: map.resolution(),
                leaves,
                details: d,
            });
        }
        if bytes.starts_with(&SNAPSHOT_MAGIC) {
            let v =
                SnapshotView::open_checked(&bytes).map_err(|e| anyhow::anyhow!("{name}: {e}"))?;
            let (known, occ) = v.counts();
            d.push((
                "format",
                format!("voxmap snapshot, version {}", v.header().version),
            ));
            d.push(("resolution", format!("{} m", v.resolution())));
            d.push(("sequence", v.sequence().to_string()));
            d.push(("timestamp", format!("{} ns", v.timestamp_ns())));
            d.push(("leaves", v.leaf_count().to_string()));
            d.push(("occupied voxels", occ.to_string()));
            d.push(("free voxels", (known - occ).to_string()));
            d.push((
                "log-odds values",
                if v.has_values() {
                    "stored"
                } else {
                    "not stored"
                }
                .into(),
            ));
            d.push(("size", format!("{} bytes (checksum verified)", bytes.len())));
            let leaves: Vec<_> = v.leaf_occupancy().collect();
            push_bounds(&mut d, &leaves, v.resolution());
            return Ok(Self {
                resolution: v.resolution(),
                leaves,
                details: d,
            });
        }
        if bytes.starts_with(b"# Octomap OcTree binary file") {
            let s = octomap::read_bt(&bytes).map_err(|e| anyhow::anyhow!("{name}: {e}"))?;
            let (res, leaves) = octomap::decode_bt(&bytes, MAX_BT_VOXELS)
                .map_err(|e| anyhow::anyhow!("{name}: {e}"))?;
            d.push(("format", "OctoMap binary tree (.bt)".into()));
            d.push(("resolution", format!("{res} m")));
            d.push(("tree nodes", s.nodes.to_string()));
            d.push(("occupied voxels", s.occupied_voxels.to_string()));
            d.push(("free voxels", s.free_voxels.to_string()));
            push_bounds(&mut d, &leaves, res);
            return Ok(Self {
                resolution: res,
                leaves,
                details: d,
            });
        }
        let head: String = bytes.iter().take(8).map(|b| format!("{b:02x}")).collect();
        bail!(
            "{name}: not a voxmap map file, snapshot file or OctoMap .bt file (first bytes {head})"
        )
    }
}

fn push_bounds(d: &mut Vec<(&'static str, String)>, leaves: &[LeafOccupancy], res: f64) {
    let mut lo = [i32::MAX; 3];
    let mut hi = [i32::MIN; 3];
    for l in leaves {
        for i in l.known.iter_ones() {
            let v = voxel_at(l.origin, i).to_array();
            for k in 0..3 {
                lo[k] = lo[k].min(v[k]);
                hi[k] = hi[k].max(v[k]);
            }
        }
    }
    let b = if lo[0] > hi[0] {
        "empty".to_string()
    } else {
        let m = |v: i32| format!("{:.2}", v as f64 * res);
        format!(
            "x {}..{} y {}..{} z {}..{} m",
            m(lo[0]),
            m(hi[0] + 1),
            m(lo[1]),
            m(hi[1] + 1),
            m(lo[2]),
            m(hi[2] + 1)
        )
    };
    d.push(("bounds (known)", b));
}

#[derive(Args, Debug)]
pub struct InspectArgs {
    /// Map file, snapshot file, OctoMap .bt file, ROS 2 bag (directory, .mcap, .db3), or
    /// tile store (directory).
    pub file: PathBuf,
    /// For a tile store: read and check every tile record too.
    #[arg(long)]
    pub check: bool,
}

pub fn inspect(a: InspectArgs) -> Result<()> {
    if voxmap_map::store::exists(&a.file) {
        return inspect_store(&a.file, a.check);
    }
    if voxmap_ros::bag::is_bag(&a.file) {
        return crate::bags::inspect(&a.file);
    }
    let l = Loaded::read(&a.file)?;
    println!("{}", a.file.display());
    for (k, v) in &l.details {
        println!("  {k:<20} {v}");
    }
    Ok(())
}

#[derive(Args, Debug)]
pub struct ExportArgs {
    /// Map file or snapshot file (or a .bt, to convert to PLY), or a tile store
    /// (directory).
    pub input: PathBuf,
    /// From a tile store: write its map as a map file (.vxm) here.
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Write OctoMap's binary tree format here.
    #[arg(long)]
    pub bt: Option<PathBuf>,
    /// Write occupied voxel centres, coloured by height, as PLY here.
    #[arg(long)]
    pub ply: Option<PathBuf>,
    /// Write a whole-map snapshot file here (what the C, C++ and Python views open; from
    /// a map file it keeps the log-odds, for probabilities).
    #[arg(long)]
    pub snapshot: Option<PathBuf>,
    /// With --snapshot from a map file: carry its distance field, to this distance (m).
    #[arg(long, value_name = "METRES")]
    pub esdf_max_distance: Option<f64>,
    /// With --esdf-max-distance: what unknown voxels count as, free or occupied.
    #[arg(long, default_value = "free")]
    pub esdf_unknown: voxmap_map::field::UnknownPolicy,
}

pub fn export(mut a: ExportArgs) -> Result<()> {
    if voxmap_map::store::exists(&a.input) {
        let out = a
            .out
            .clone()
            .context("a tile store exports to a map file first: pass --out MAP.vxm")?;
        let leaves = voxmap_map::store::export(&a.input, &out)?;
        println!(
            "wrote {}: map file of the tile store {} ({leaves} leaves)",
            out.display(),
            a.input.display()
        );
        if a.bt.is_none() && a.ply.is_none() && a.snapshot.is_none() {
            return Ok(());
        }
        a.input = out;
    } else if a.out.is_some() {
        bail!(
            "--out is for a tile store; {} holds none",
            a.input.display()
        );
    }
    if a.bt.is_none() && a.ply.is_none() && a.snapshot.is_none() {
        bail!("nothing to do: pass --bt OUT.bt, --ply OUT.ply and/or --snapshot OUT");
    }
    if let Some(out) = &a.snapshot {
        let bytes = match a.esdf_max_distance {
            None => mapfile::read_as_snapshot(&a.input)?,
            Some(max_distance) => {
                let cfg = voxmap_map::field::FieldConfig {
                    max_distance,
                    unknown: a.esdf_unknown,
                    window: None,
                };
                mapfile::read_as_snapshot_with_field(&a.input, &cfg)?
            }
        };
        mapfile::save_snapshot(&bytes, out)?;
        let v = SnapshotView::open(&bytes)?;
        let (known, occupied) = v.counts();
        println!(
            "wrote {}: snapshot of {} leaves, {known} known and {occupied} occupied voxels at {} m",
            out.display(),
            v.leaf_count(),
            v.resolution()
        );
        if a.bt.is_none() && a.ply.is_none() {
            return Ok(());
        }
    }
    let l = Loaded::read(&a.input)?;
    if let Some(out) = &a.bt {
        let bytes = octomap::encode_bt(l.leaves.iter().copied(), l.resolution)
            .map_err(|e| anyhow::anyhow!("{}: {e}", a.input.display()))?;
        mapfile::write_atomic(out, &bytes)?;
        let s = octomap::read_bt(&bytes)?;
        println!(
            "wrote {}: {} nodes, {} occupied and {} free voxels at {} m",
            out.display(),
            s.nodes,
            s.occupied_voxels,
            s.free_voxels,
            l.resolution
        );
    }
    if let Some(out) = &a.ply {
        let n = occupied_count(&l.leaves);
        if n > MAX_PLY_POINTS {
            bail!(
                "{}: {n} occupied voxels is more than a PLY export writes ({MAX_PLY_POINTS})",
                a.input.display()
            );
        }
        let bytes = ply::encode_colored(&occupied_colored(&l.leaves, l.resolution));
        mapfile::write_atomic(out, &bytes)?;
        println!(
            "wrote {}: {} occupied voxel centres",
            out.display(),
            occupied_count(&l.leaves)
        );
    }
    Ok(())
}

fn occupied_count(leaves: &[LeafOccupancy]) -> u64 {
    leaves.iter().map(|l| l.occupied.count() as u64).sum()
}

/// Occupied voxel centres with colours by height across the occupied range.
fn occupied_colored(leaves: &[LeafOccupancy], res: f64) -> Vec<([f32; 3], [u8; 3])> {
    let mut pts: Vec<[f64; 3]> = Vec::new();
    for l in leaves {
        for i in l.occupied.iter_ones() {
            let v = voxel_at(l.origin, i).to_array();
            pts.push(v.map(|c| (c as f64 + 0.5) * res));
        }
    }
    let (lo, hi) = pts.iter().fold((f64::MAX, f64::MIN), |(lo, hi), p| {
        (lo.min(p[2]), hi.max(p[2]))
    });
    pts.iter()
        .map(|p| {
            let t = (p[2] - lo) / (hi - lo).max(1e-9);
            (p.map(|c| c as f32), ply::height_color(t))
        })
        .collect()
}

/// `voxmap inspect STORE_DIR`: the manifest, the segments, and with `check` every record.
fn inspect_store(dir: &Path, check: bool) -> Result<()> {
    use voxmap_map::store::TileStore;
    let (mut store, m) = TileStore::open_read_only(dir)?;
    let leaves: u64 = m.tiles.iter().map(|e| u64::from(e.leaves)).sum();
    let live: u64 = m.tiles.iter().map(|e| u64::from(e.len)).sum();
    let raw = leaves * mapfile::RECORD as u64;
    let disk = store.counters().disk_bytes;
    let segments: std::collections::BTreeSet<u32> = m.tiles.iter().map(|e| e.segment).collect();
    println!("{} (tile store)", dir.display());
    let p = &m.params;
    for (k, v) in [
        ("resolution", format!("{} m", p.resolution)),
        ("sensor model", format!("{:?}", p.model)),
        (
            "distance field",
            p.field.map_or("none".into(), |f| {
                format!(
                    "to {} m, unknown as {:?}, window {:?} (bands stored with the tiles)",
                    f.max_distance, f.unknown, f.window
                )
            }),
        ),
        ("generation", m.generation.to_string()),
        (
            "last frame",
            format!("sequence {}, stamp {} ns", m.last_frame.0, m.last_frame.1),
        ),
        ("tiles", m.tiles.len().to_string()),
        ("leaves", leaves.to_string()),
        (
            "records",
            match p.field {
                None => format!(
                    "{live} bytes ({raw} uncompressed, {:.1}x)",
                    raw as f64 / live.max(1) as f64
                ),
                Some(_) => format!("{live} bytes (leaf records alone {raw} uncompressed)"),
            },
        ),
        (
            "segments",
            format!(
                "{} with live records, {disk} bytes on disk ({:.0}% live)",
                segments.len(),
                100.0 * live as f64 / disk.max(1) as f64
            ),
        ),
    ] {
        println!("  {k:<20} {v}");
    }
    if check {
        let mut bad = 0;
        for e in &m.tiles {
            if let Err(err) = store.get(voxmap_map::VoxelCoord::from_array(e.tile)) {
                println!("  refused: {err}");
                bad += 1;
            }
        }
        println!(
            "  {:<20} {} records read, {bad} refused",
            "check",
            m.tiles.len()
        );
        if bad > 0 {
            bail!("{bad} tile records of {} refused", dir.display());
        }
    }
    Ok(())
}

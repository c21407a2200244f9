//! `voxmap replay`: feed recorded scans (PCD, KITTI `.bin`, PLY, or the clouds of a ROS 2
//! bag) to a running service or straight into the core offline, writing a map file.

use crate::bags::{BagArgs, BagPlan};
use crate::config::MappingArgs;
use anyhow::{anyhow, bail, Context, Result};
use clap::{Args, ValueEnum};
use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};
use nalgebra::Isometry3;
use std::io::IsTerminal;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};
use voxmap_client::{FramePublisher, MapControl, SnapshotSubscriber};
use voxmap_ipc::FrameHeader;
use voxmap_map::io::scans::StampedPose;
use voxmap_map::io::{mapfile, pcd, ply, scans};
use voxmap_map::{Frame, FrameStamp};

#[derive(Args, Debug)]
pub struct ReplayArgs {
    /// PCD files (pose from VIEWPOINT), KITTI .bin or PLY files (pose from --poses), or
    /// directories of them, read in name order; or one ROS 2 bag (a rosbag2 directory, a
    /// .mcap or a .db3 file), its clouds posed from TF.
    #[arg(required = true)]
    pub inputs: Vec<PathBuf>,
    /// Pose file for .bin and .ply scans: KITTI (12 numbers per line) or TUM
    /// (t tx ty tz qx qy qz qw). Matched by time stamp when the scans are named by time
    /// stamps and the file has them, otherwise line i is the pose of scan i.
    #[arg(long)]
    pub poses: Option<PathBuf>,
    /// Integrate here instead of sending to a service; needs --out.
    #[arg(long, requires = "out")]
    pub offline: bool,
    /// Read (and pose) every scan and print the summary, mapping nothing: checks a
    /// recording, and times its reading on its own.
    #[arg(long, conflicts_with_all = ["offline", "save"])]
    pub dry_run: bool,
    /// Offline: write the map file here.
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Offline with --store: save the store (incrementally) every this many frames, so
    /// that a replay cut short leaves the map as of its last save.
    #[arg(long, value_name = "FRAMES", requires = "offline")]
    pub save_every: Option<u64>,
    /// Service-name prefix of the running service.
    #[arg(long, default_value = "voxmap")]
    pub prefix: String,
    #[arg(long, default_value = "default")]
    pub map: String,
    /// To a service: `fast` (each frame once the last is integrated), `recorded` (at the
    /// time stamps' pace) or a rate in Hz.
    #[arg(long, default_value = "fast")]
    pub rate: String,
    /// To a service: ask it to save its map here after the last frame.
    #[arg(long)]
    pub save: Option<PathBuf>,
    /// What to do with a file or cloud that cannot be read (or posed), or a damaged bag.
    #[arg(long, value_enum, default_value_t = OnError::Abort)]
    pub on_error: OnError,
    #[command(flatten)]
    pub bag: BagArgs,
    /// Offline mapping settings (a service uses its own).
    #[command(flatten)]
    pub mapping: MappingArgs,
}

#[derive(Clone, Copy, Debug, PartialEq, ValueEnum)]
pub enum OnError {
    Skip,
    Abort,
}

/// One recorded scan.
pub struct Scan {
    /// The file, or the bag topic and index.
    pub name: String,
    pub points: Vec<[f32; 3]>,
    /// Points the reader left out for a non-finite coordinate.
    pub non_finite: u64,
    pub pose: Isometry3<f64>,
    /// Seconds, when known (TUM poses, a file named by its time stamp, a cloud's stamp).
    pub stamp: Option<f64>,
}

/// What the reader thread hands the replay loop, in input order.
pub enum Read {
    Scan(Scan),
    /// A scan that cannot be used, with a short reason to count it by.
    Skip {
        kind: String,
        error: anyhow::Error,
    },
    /// A damaged bag file: what was before the damage has been sent.
    Damaged(anyhow::Error),
    /// A transform or pose message that could not go into the TF buffer.
    TfRejected(String),
}

const EXTENSIONS: [&str; 3] = ["pcd", "bin", "ply"];

/// Files to replay: directories expanded to their scans in name order.
pub fn list_inputs(inputs: &[PathBuf]) -> Result<Vec<PathBuf>> {
    let mut out = Vec::new();
    for p in inputs {
        if p.is_dir() {
            let mut v: Vec<PathBuf> = std::fs::read_dir(p)
                .with_context(|| format!("reading {}", p.display()))?
                .filter_map(|e| e.ok().map(|e| e.path()))
                .filter(|f| {
                    f.extension()
                        .is_some_and(|e| EXTENSIONS.iter().any(|x| e == *x))
                })
                .collect();
            v.sort();
            out.extend(v);
        } else {
            out.push(p.clone());
        }
    }
    if out.is_empty() {
        bail!("no .pcd, .bin or .ply files in {inputs:?}");
    }
    Ok(out)
}

fn stem_stamp(path: &Path) -> Option<f64> {
    path.file_stem()?
        .to_str()?
        .parse::<f64>()
        .ok()
        .filter(|t| t.is_finite())
}

/// Read scan `index` of the list; `poses` for the formats without an embedded pose.
pub fn read_scan(path: &Path, index: usize, poses: Option<&[StampedPose]>) -> Result<Scan> {
    let ext = path.extension().and_then(|e| e.to_str()).unwrap_or("");
    if ext == "pcd" {
        let c = pcd::read(path)?;
        return Ok(Scan {
            name: path.display().to_string(),
            non_finite: 0,
            points: c.points,
            pose: c.pose,
            stamp: stem_stamp(path),
        });
    }
    let bytes = std::fs::read(path).with_context(|| format!("reading {}", path.display()))?;
    let points = match ext {
        "bin" => scans::parse_kitti_bin(&bytes),
        "ply" => ply::parse(&bytes),
        _ => bail!(
            "{}: unknown extension '{ext}' (pcd, bin, ply)",
            path.display()
        ),
    }
    .with_context(|| path.display().to_string())?;
    let poses =
        poses.ok_or_else(|| anyhow!("{}: .{ext} scans need --poses FILE", path.display()))?;
    let stamp = stem_stamp(path);
    let p = match (stamp, poses.first().and_then(|p| p.stamp)) {
        (Some(t), Some(_)) => {
            let i = poses.partition_point(|p| p.stamp.unwrap_or(f64::MIN) < t);
            let best = [i.saturating_sub(1), i.min(poses.len() - 1)]
                .into_iter()
                .min_by(|&a, &b| {
                    let d = |k: usize| (poses[k].stamp.unwrap_or(f64::MAX) - t).abs();
                    d(a).total_cmp(&d(b))
                })
                .map(|k| poses[k])
                .ok_or_else(|| anyhow!("empty pose file"))?;
            let dt = (best.stamp.unwrap_or(f64::MAX) - t).abs();
            if dt > 0.05 {
                bail!(
                    "{}: nearest pose is {dt:.3} s away (more than 0.05 s)",
                    path.display()
                );
            }
            best
        }
        _ => *poses.get(index).ok_or_else(|| {
            anyhow!(
                "{}: scan {} has no pose (the pose file has {} lines)",
                path.display(),
                index + 1,
                poses.len()
            )
        })?,
    };
    Ok(Scan {
        name: path.display().to_string(),
        non_finite: 0,
        points,
        pose: p.pose,
        stamp: p.stamp.or(stamp),
    })
}

/// Where scans go: integrated offline, or sent to a service.
enum Sink {
    Offline(Box<Offline>),
    Service(Box<Online>),
    DryRun,
}

struct Offline {
    /// The map, kept as the service keeps it (with its distance field under `--esdf`).
    mapper: voxmap_map::Mapper,
    out: PathBuf,
    /// The distance field's update times (ms).
    field_ms: Vec<f64>,
    /// Integration time, seconds.
    integrate_s: f64,
    /// Save the store every this many frames.
    save_every: Option<u64>,
    /// Each frame's time (ms): integration, and with a tile store the tiles it waited for
    /// and the evictions after it.
    frame_ms: Vec<f64>,
}

struct Online {
    publisher: FramePublisher,
    snapshots: SnapshotSubscriber,
    control: MapControl,
    /// With `--rate fast`: wait for each frame's snapshot before sending the next.
    wait: bool,
}

/// Where scans come from.
enum Source {
    Files(Vec<PathBuf>),
    Bag(Box<BagPlan>),
}

/// What the replay counted on the way.
#[derive(Default)]
struct Tally {
    frames: u64,
    points: u64,
    non_finite: u64,
    skipped: Skipped,
}

pub fn run(a: ReplayArgs) -> Result<()> {
    let source = Source::open(&a)?;
    let total = source.len();
    let poses = read_poses(a.poses.as_deref())?;
    let mut pacer = Pacer::new(&a.rate)?;
    let mut sink = Sink::open(&a, pacer.rate.is_none())?;
    // The clock starts once the sink is ready (a service has answered).
    pacer.started = Instant::now();
    // Read ahead on a second thread so reading overlaps integration.
    let (rx, reader) = source.spawn(poses);
    let bar = ProgressBar::with_draw_target(total, ProgressDrawTarget::stderr());
    bar.set_style(
        ProgressStyle::with_template("{bar:30} {pos}/{len} frames  {msg}")
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    let plain = !std::io::stderr().is_terminal();
    let mut last_line = Instant::now();
    let mut tally = Tally::default();
    for item in rx {
        let Some(scan) = tally.take(item, a.on_error, &bar)? else {
            continue;
        };
        pacer.wait(&scan, tally.frames)?;
        if !sink.take(&scan, tally.frames, a.on_error, &bar, &mut tally.skipped)? {
            continue;
        }
        tally.frames += 1;
        tally.points += scan.points.len() as u64;
        tally.non_finite += scan.non_finite;
        bar.inc(1);
        let secs = pacer.started.elapsed().as_secs_f64().max(1e-9);
        let msg = format!(
            "{:.1} frames/s, {:.2} Mpoints/s",
            tally.frames as f64 / secs,
            tally.points as f64 / secs / 1e6
        );
        if plain && last_line.elapsed() >= Duration::from_secs(2) {
            let of = total.map_or(String::new(), |t| format!("/{t}"));
            eprintln!("voxmap replay: {}{of} frames, {msg}", tally.frames);
            last_line = Instant::now();
        }
        bar.set_message(msg);
    }
    bar.finish_and_clear();
    reader
        .join()
        .map_err(|_| anyhow!("reader thread panicked"))?;
    let secs = pacer.started.elapsed().as_secs_f64();
    let Tally {
        frames,
        points,
        non_finite,
        skipped,
    } = &tally;
    println!(
        "replayed {frames} frames ({points} points) in {secs:.2} s: {:.1} frames/s, {:.2} Mpoints/s{}{}",
        *frames as f64 / secs.max(1e-9),
        *points as f64 / secs.max(1e-9) / 1e6,
        if *non_finite > 0 { format!("; {non_finite} non-finite points skipped") } else { String::new() },
        skipped.summary()
    );
    sink.finish(*points, a.save.as_deref())
}

/// The pose file, sorted by stamp when every line has one.
fn read_poses(path: Option<&Path>) -> Result<Option<Vec<StampedPose>>> {
    let Some(p) = path else {
        return Ok(None);
    };
    let text = std::fs::read_to_string(p).with_context(|| format!("reading {}", p.display()))?;
    let mut v = scans::parse_poses(&text).with_context(|| p.display().to_string())?;
    if v.iter().all(|p| p.stamp.is_some()) {
        v.sort_by(|x, y| x.stamp.unwrap_or(0.0).total_cmp(&y.stamp.unwrap_or(0.0)));
    }
    Ok(Some(v))
}

impl Source {
    fn open(a: &ReplayArgs) -> Result<Self> {
        Ok(match a.inputs.as_slice() {
            [one] if voxmap_ros::bag::is_bag(one) => {
                Source::Bag(Box::new(BagPlan::new(one, &a.bag)?))
            }
            many => {
                if let Some(b) = many.iter().find(|p| voxmap_ros::bag::is_bag(p)) {
                    bail!(
                        "{}: a ROS 2 bag is replayed on its own, not with other inputs",
                        b.display()
                    );
                }
                Source::Files(list_inputs(many)?)
            }
        })
    }

    /// How many scans it holds, where known.
    fn len(&self) -> Option<u64> {
        match self {
            Source::Files(f) => Some(f.len() as u64),
            Source::Bag(b) => b.cloud_count,
        }
    }

    /// Read the scans in order on a thread of their own, two ahead of the replay.
    fn spawn(
        self,
        poses: Option<Vec<StampedPose>>,
    ) -> (std::sync::mpsc::Receiver<Read>, std::thread::JoinHandle<()>) {
        let (tx, rx) = std::sync::mpsc::sync_channel::<Read>(2);
        let reader = std::thread::spawn(move || match self {
            Source::Files(files) => {
                for (i, f) in files.iter().enumerate() {
                    let r = match read_scan(f, i, poses.as_deref()) {
                        Ok(s) => Read::Scan(s),
                        Err(e) => Read::Skip {
                            kind: "unreadable file".into(),
                            error: e.context(format!("scan {} of {}", i + 1, files.len())),
                        },
                    };
                    if tx.send(r).is_err() {
                        break;
                    }
                }
            }
            Source::Bag(plan) => plan.read(&mut |r| tx.send(r).is_ok()),
        });
        (rx, reader)
    }
}

impl Tally {
    /// The scan of `item`, or `None` for what is skipped and counted (under `--on-error
    /// skip`), or the error that ends the replay.
    fn take(&mut self, item: Read, on_error: OnError, bar: &ProgressBar) -> Result<Option<Scan>> {
        match item {
            Read::Scan(s) => Ok(Some(s)),
            Read::Skip { kind, error } if on_error == OnError::Skip => {
                bar.suspend(|| eprintln!("voxmap replay: skipping: {error:#}"));
                self.skipped.add(kind);
                bar.inc(1);
                Ok(None)
            }
            Read::Damaged(e) if on_error == OnError::Skip => {
                bar.suspend(|| eprintln!("voxmap replay: {e:#}; going on with what follows"));
                self.skipped.add("damaged bag file".into());
                Ok(None)
            }
            Read::Skip { error, .. } | Read::Damaged(error) => Err(error),
            Read::TfRejected(why) => {
                if self.skipped.transforms == 0 {
                    bar.suspend(|| eprintln!("voxmap replay: transform ignored: {why}"));
                }
                self.skipped.transforms += 1;
                Ok(None)
            }
        }
    }
}

/// Paces the scans: as fast as they go, at their stamps' pace, or at a rate.
struct Pacer {
    /// `None`: fast; `Some(0.0)`: recorded; else Hz.
    rate: Option<f64>,
    started: Instant,
    first_stamp: Option<(f64, Instant)>,
}

impl Pacer {
    fn new(rate: &str) -> Result<Self> {
        let rate = match rate {
            "fast" => None,
            "recorded" => Some(0.0),
            hz => Some(
                hz.parse::<f64>()
                    .ok()
                    .filter(|h| (0.001..=1e6).contains(h))
                    .ok_or_else(|| {
                        anyhow!(
                            "--rate must be fast, recorded or a rate in Hz in [0.001, 1e6], not '{hz}'"
                        )
                    })?,
            ),
        };
        Ok(Pacer {
            rate,
            started: Instant::now(),
            first_stamp: None,
        })
    }

    /// Sleep until `scan`, the `frames`-th, is due.
    fn wait(&mut self, scan: &Scan, frames: u64) -> Result<()> {
        let due = match self.rate {
            None => return Ok(()),
            Some(0.0) => {
                let t = scan.stamp.ok_or_else(|| {
                    anyhow!(
                        "{}: no time stamp for --rate recorded (use fast or a rate in Hz)",
                        scan.name
                    )
                })?;
                let (t0, w0) = *self.first_stamp.get_or_insert((t, Instant::now()));
                // Stamps in seconds: a day between scans means they are in another unit.
                let gap = Duration::try_from_secs_f64((t - t0).max(0.0))
                    .ok()
                    .filter(|g| *g <= Duration::from_secs(86_400))
                    .ok_or_else(|| {
                        anyhow!(
                            "{}: stamp {t} s is more than a day after the first ({t0} s); \
                             are the names nanoseconds? use --rate fast or a rate in Hz",
                            scan.name
                        )
                    })?;
                w0 + gap
            }
            Some(hz) => self.started + Duration::from_secs_f64(frames as f64 / hz),
        };
        std::thread::sleep(due.saturating_duration_since(Instant::now()));
        Ok(())
    }
}

impl Sink {
    /// The sink the arguments ask for; `wait`: a service's frames are sent one at a time,
    /// each once the last is integrated.
    fn open(a: &ReplayArgs, wait: bool) -> Result<Self> {
        if a.dry_run {
            return Ok(Sink::DryRun);
        }
        if a.offline {
            let cfg = a.mapping.resolve()?;
            return Ok(Sink::Offline(Box::new(Offline {
                mapper: cfg.mapper()?,
                out: a.out.clone().context("--offline needs --out MAP")?,
                field_ms: Vec::new(),
                integrate_s: 0.0,
                frame_ms: Vec::new(),
                save_every: a.save_every.filter(|&n| n > 0),
            })));
        }
        let control = MapControl::connect(&a.prefix, &a.map)
            .map_err(|e| anyhow!("no voxmap service under prefix '{}': {e}", a.prefix))?;
        let mut snapshots = SnapshotSubscriber::connect(&a.prefix, &a.map)?;
        wait_for_service(&mut snapshots, &a.prefix)?;
        Ok(Sink::Service(Box::new(Online {
            publisher: FramePublisher::connect(&a.prefix, &a.map)?,
            snapshots,
            control,
            wait,
        })))
    }

    /// Map or send `scan`, the `frames`-th; returns false where it was skipped (and
    /// counted) under `--on-error skip`.
    fn take(
        &mut self,
        scan: &Scan,
        frames: u64,
        on_error: OnError,
        bar: &ProgressBar,
        skipped: &mut Skipped,
    ) -> Result<bool> {
        match self {
            Sink::DryRun => {}
            Sink::Offline(off) => {
                let frame = Frame {
                    pose: scan.pose,
                    points: &scan.points,
                };
                let stamp = FrameStamp {
                    sequence: frames + 1,
                    stamp_ns: scan.stamp.map_or(0, |s| (s * 1e9) as u64),
                };
                match off.mapper.insert(&frame, stamp) {
                    Ok(rep) => {
                        let mut t = rep.integrate.times.total().as_secs_f64();
                        if let Some(tiles) = &rep.tiles {
                            t += (tiles.load_time + tiles.evict_time).as_secs_f64();
                            for e in tiles.refused.iter().chain(&tiles.write_error) {
                                bar.suspend(|| eprintln!("voxmap replay: tile store: {e}"));
                            }
                        }
                        off.integrate_s += t;
                        off.frame_ms.push(t * 1e3);
                        if off
                            .save_every
                            .is_some_and(|n| (frames + 1).is_multiple_of(n))
                        {
                            let r = off
                                .mapper
                                .save_store()
                                .context("--save-every needs --store")?;
                            let r = r.context("saving the tile store")?;
                            bar.suspend(|| {
                                println!(
                                    "store saved: frame {}, generation {}, {} tiles written",
                                    frames + 1,
                                    r.generation,
                                    r.tiles_written
                                )
                            });
                        }
                        if let Some(f) = &rep.field {
                            off.field_ms.push(f.time.as_secs_f64() * 1e3);
                        }
                    }
                    Err(e) if on_error == OnError::Abort => bail!("{}: {e}", scan.name),
                    Err(e) => {
                        bar.suspend(|| eprintln!("voxmap replay: skipping {}: {e}", scan.name));
                        skipped.add("rejected by the integrator".into());
                        bar.inc(1);
                        return Ok(false);
                    }
                }
            }
            Sink::Service(online) => {
                if let Err(e) = FrameHeader::with_pose(&scan.pose).validate(0) {
                    bail!("{}: {e}", scan.name);
                }
                let stamp_ns = crate::os::now_ns();
                let seq = online
                    .publisher
                    .publish(&scan.pose, stamp_ns, &scan.points)?;
                if online.wait {
                    wait_integrated(&mut online.snapshots, &online.control, seq)
                        .with_context(|| scan.name.clone())?;
                }
            }
        }
        Ok(true)
    }

    /// After the last scan: write the map file (offline), or report the service's counts
    /// and ask it to save to `save`.
    fn finish(self, points: u64, save: Option<&Path>) -> Result<()> {
        match self {
            Sink::DryRun => {}
            Sink::Offline(off) => {
                let Offline {
                    mut mapper,
                    out,
                    mut field_ms,
                    integrate_s,
                    mut frame_ms,
                    save_every: _,
                } = *off;
                frame_ms.sort_by(f64::total_cmp);
                let q = |p| crate::quantile::percentile(&frame_ms, p);
                println!(
                    "frames: {} ms p50 {:.2}, p99 {:.2}, max {:.2}; peak RSS {}",
                    frame_ms.len(),
                    q(0.5),
                    q(0.99),
                    frame_ms.last().copied().unwrap_or(0.0),
                    crate::os::peak_rss().map_or("unknown".into(), |b| format!("{} MiB", b >> 20))
                );
                if let Some(t) = mapper.tile_stats() {
                    let leaves = mapper
                        .write_map_file(&out)
                        .with_context(|| format!("writing {}", out.display()))?;
                    let saved = mapper
                        .save_store()
                        .context("no store")?
                        .context("saving the tile store")?;
                    println!(
                        "tile store {}: {t}; saved ({} tiles written, generation {})",
                        mapper
                            .store_dir()
                            .map_or(String::new(), |d| d.display().to_string()),
                        saved.tiles_written,
                        saved.generation
                    );
                    println!(
                        "integration {integrate_s:.2} s ({:.2} Mpoints/s), with the tiles' loads and evictions",
                        points as f64 / integrate_s.max(1e-9) / 1e6
                    );
                    println!("wrote {} ({leaves} leaves)", out.display());
                    return Ok(());
                }
                let (map, field) = mapper.into_parts();
                let c = map.counts();
                println!(
                    "integration {integrate_s:.2} s ({:.2} Mpoints/s); map: {} occupied, {} free voxels, {} leaves, {} bytes",
                    points as f64 / integrate_s.max(1e-9) / 1e6,
                    c.occupied,
                    c.free,
                    c.leaves,
                    map.memory_bytes()
                );
                if let Some(f) = &field {
                    let total: f64 = field_ms.iter().sum();
                    field_ms.sort_by(f64::total_cmp);
                    println!(
                        "distance field: {} updates, {total:.1} ms in all, median {:.2} ms, max {:.2} ms; {} voxels in the band, {} bytes",
                        field_ms.len(),
                        crate::quantile::percentile(&field_ms, 0.5),
                        field_ms.last().copied().unwrap_or(0.0),
                        f.band_voxels(),
                        f.memory_bytes()
                    );
                }
                mapfile::save_map_with_field(&map, field.as_ref(), &out)?;
                println!(
                    "wrote {}{}",
                    out.display(),
                    if field.is_some() {
                        " (with its distance field)"
                    } else {
                        ""
                    }
                );
            }
            Sink::Service(online) => {
                let control = &online.control;
                let s = control.stats()?;
                println!(
                    "service: {} frames integrated, {} dropped, {} rejected; map {} leaves, {} bytes; snapshot {} bytes",
                    s.frames_integrated, s.frames_dropped, s.frames_rejected, s.map_leaves, s.map_memory_bytes, s.snapshot_bytes
                );
                if let Some(p) = save {
                    let abs = std::path::absolute(p).unwrap_or_else(|_| p.to_path_buf());
                    control.save(&abs.to_string_lossy())?;
                    println!("service saved its map to {}", abs.display());
                }
            }
        }
        Ok(())
    }
}

/// Scans and transforms left out, by reason.
#[derive(Default)]
struct Skipped {
    by_kind: Vec<(String, u64)>,
    transforms: u64,
}

impl Skipped {
    fn add(&mut self, kind: String) {
        match self.by_kind.iter_mut().find(|(k, _)| *k == kind) {
            Some((_, n)) => *n += 1,
            None => self.by_kind.push((kind, 1)),
        }
    }

    /// `; 3 skipped (2 no transform (...), 1 data size disagrees); 4 transforms ignored`.
    fn summary(&self) -> String {
        let mut s = String::new();
        let n: u64 = self.by_kind.iter().map(|(_, n)| n).sum();
        if n > 0 {
            let parts: Vec<String> = self
                .by_kind
                .iter()
                .map(|(k, n)| format!("{n} {k}"))
                .collect();
            s += &format!("; {n} skipped ({})", parts.join(", "));
        }
        if self.transforms > 0 {
            s += &format!("; {} transforms ignored", self.transforms);
        }
        s
    }
}

/// Wait for the service's first snapshot. The service subscribes to frames before it
/// publishes one, and frames sent before it subscribes are lost (no history), so this is
/// how replay knows its first frame will arrive; it also catches a service that is not
/// running, which connecting alone does not (connect creates the services if absent).
fn wait_for_service(snapshots: &mut SnapshotSubscriber, prefix: &str) -> Result<()> {
    // A new subscriber holds no snapshot, so any snapshot is an update.
    if !snapshots.wait_for_update(Duration::from_secs(30))? {
        bail!("no voxmap service under prefix '{prefix}': no snapshot after 30 s");
    }
    Ok(())
}

/// Wait until the service publishes a snapshot that includes frame `seq`.
fn wait_integrated(
    snapshots: &mut SnapshotSubscriber,
    control: &MapControl,
    seq: u64,
) -> Result<()> {
    let t = Instant::now();
    loop {
        if let Some(v) = snapshots.latest()? {
            if v.sequence() >= seq {
                return Ok(());
            }
        }
        if t.elapsed() > Duration::from_secs(30) {
            let s = control.stats()?;
            bail!(
                "the service has not published frame {seq} after 30 s (it integrated {}, dropped {}, rejected {})",
                s.frames_integrated,
                s.frames_dropped,
                s.frames_rejected
            );
        }
        snapshots.wait_for_update(Duration::from_millis(100))?;
    }
}

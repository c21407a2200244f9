//! Settings shared by `serve` and `replay`: the embedded defaults (`default.toml`), then
//! an optional TOML file (`--config`), then command-line flags, each overriding the last.

use anyhow::{bail, Context, Result};
use clap::Args;
use serde::{Deserialize, Serialize};
use std::path::PathBuf;
use voxmap_ipc::ports::qos::FRAME_SUBSCRIBER_BUFFER;
use voxmap_map::field::{FieldConfig, UnknownPolicy};
use voxmap_map::mapper::StoreConfig;
use voxmap_map::{
    Integrator, IntegratorConfig, Mapper, MapperConfig, OccupancyMap, RayMode, SensorModel,
};

/// The embedded defaults: `voxmap serve` with no file and no flags runs on these.
pub const DEFAULT_TOML: &str = include_str!("../default.toml");

/// How rays are chosen from a frame's points (with `subsample_factor` and
/// `bundle_threshold`, a [`RayMode`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "snake_case")]
#[value(rename_all = "snake_case")]
pub enum Mode {
    Exact,
    Subsample,
    Bundle,
    UniqueEnd,
}

/// What the service does with frames that arrive faster than it integrates them.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "snake_case")]
pub enum Intake {
    /// The newest waiting frame wins; the others are dropped and counted.
    Latest,
    /// Up to `queue_depth` waiting frames are integrated in order.
    Queue,
}

impl std::fmt::Display for Intake {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Self::Latest => "latest",
            Self::Queue => "queue",
        })
    }
}

/// Every setting, as the TOML file spells it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Config {
    pub prefix: String,
    pub map: String,
    pub resolution: f64,
    pub max_range: f64,
    /// 0 = one per core.
    pub threads: usize,
    /// Pin integration thread i to the i-th CPU the service may use.
    pub pin_threads: bool,
    pub mode: Mode,
    pub subsample_factor: u32,
    pub bundle_threshold: u32,
    pub sensor_model: SensorModel,
    pub snapshot_values: bool,
    /// Publish at most one snapshot per this many milliseconds (0 = after every frame).
    pub snapshot_interval_ms: f64,
    pub intake: Intake,
    /// Frames kept waiting under `intake = "queue"` (1..=4).
    pub queue_depth: usize,
    /// SCHED_FIFO priority of the service's frame/snapshot thread (0 = normal scheduling).
    pub rt_priority: i32,
    /// Live ROS 2 (`voxmap serve --ros2`).
    pub ros2: voxmap_ros2::Ros2Config,
    /// The distance field.
    pub esdf: EsdfConfig,
    /// Keep the map in a tile store in this directory ("" = none).
    pub store: String,
    /// Keep the map's resident bytes under this ("256M", "2G", bytes, or "unlimited");
    /// needs a store.
    pub memory_budget: String,
    /// With a store, `serve` saves it this often (seconds) when frames came since; 0 = only
    /// on request and at exit.
    pub store_save_interval_s: f64,
}

/// `[esdf]`: whether the service keeps a distance field, and its [`FieldConfig`].
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EsdfConfig {
    pub enabled: bool,
    pub max_distance: f64,
    pub unknown: UnknownPolicy,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub window: Option<[f64; 3]>,
}

/// Flags that override the configuration, for `serve` and `replay` alike.
#[derive(Args, Debug, Clone, Default)]
pub struct MappingArgs {
    /// TOML file with any of the settings in `voxmap config` (flags override it).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Voxel edge, metres.
    #[arg(long)]
    pub resolution: Option<f64>,
    /// Rays are cut here (metres) and mark free space only.
    #[arg(long)]
    pub max_range: Option<f64>,
    /// Integration threads (0 = one per core).
    #[arg(long)]
    pub threads: Option<usize>,
    /// Pin integration thread i to the i-th CPU the service may use: true or false.
    #[arg(long)]
    pub pin_threads: Option<bool>,
    /// Ray selection.
    #[arg(long, value_enum)]
    pub mode: Option<Mode>,
    /// For --mode subsample: sub-cells per voxel edge.
    #[arg(long)]
    pub subsample_factor: Option<u32>,
    /// For --mode bundle: points per bundle above which one ray is cast.
    #[arg(long)]
    pub bundle_threshold: Option<u32>,
    /// Sensor model: P(occupied | hit).
    #[arg(long)]
    pub p_hit: Option<f64>,
    /// Sensor model: P(occupied | ray passed).
    #[arg(long)]
    pub p_miss: Option<f64>,
    /// Sensor model: lower clamping probability.
    #[arg(long)]
    pub clamp_min: Option<f64>,
    /// Sensor model: upper clamping probability.
    #[arg(long)]
    pub clamp_max: Option<f64>,
    /// Sensor model: occupancy threshold.
    #[arg(long)]
    pub occupancy_threshold: Option<f64>,
    /// Keep a distance field (ESDF) beside the map (`[esdf] enabled`).
    #[arg(long)]
    pub esdf: bool,
    /// Distance field: distances kept below this (metres).
    #[arg(long)]
    pub esdf_max_distance: Option<f64>,
    /// Distance field: what unknown voxels count as, free or occupied.
    #[arg(long)]
    pub esdf_unknown: Option<UnknownPolicy>,
    /// Distance field: only in a box of these half-extents (metres, X,Y,Z) around the
    /// sensor.
    #[arg(long, value_delimiter = ',', num_args = 3, value_name = "X,Y,Z")]
    pub esdf_window: Option<Vec<f64>>,
    /// Keep the map in a tile store in this directory, continuing the one there if any:
    /// saves write only the tiles changed, and with --memory-budget far tiles live there.
    #[arg(long, value_name = "DIR")]
    pub store: Option<PathBuf>,
    /// Keep the map's resident bytes under this (suffixes K, M, G: binary multiples; or
    /// "unlimited"), evicting the least recently observed tiles to --store.
    #[arg(long, value_name = "BYTES")]
    pub memory_budget: Option<String>,
}

impl MappingArgs {
    /// Defaults, then the file, then these flags.
    pub fn resolve(&self) -> Result<Config> {
        let mut c: Config = toml::from_str(DEFAULT_TOML).context("embedded default.toml")?;
        if let Some(p) = &self.config {
            let text =
                std::fs::read_to_string(p).with_context(|| format!("reading {}", p.display()))?;
            c = merge_toml(&c, &text).with_context(|| format!("config file {}", p.display()))?;
        }
        macro_rules! set {
            ($($flag:ident => $($field:ident).+),* $(,)?) => {
                $(if let Some(v) = self.$flag.clone() { c.$($field).+ = v; })*
            };
        }
        set!(resolution => resolution, max_range => max_range, threads => threads, pin_threads => pin_threads, mode => mode,
             subsample_factor => subsample_factor, bundle_threshold => bundle_threshold,
             p_hit => sensor_model.p_hit, p_miss => sensor_model.p_miss,
             clamp_min => sensor_model.clamp_min, clamp_max => sensor_model.clamp_max,
             occupancy_threshold => sensor_model.occupancy_threshold,
             esdf_max_distance => esdf.max_distance, esdf_unknown => esdf.unknown);
        c.esdf.enabled |= self.esdf;
        if let Some(d) = &self.store {
            c.store = d.to_string_lossy().into_owned();
        }
        if let Some(b) = &self.memory_budget {
            c.memory_budget = b.clone();
        }
        if let Some(w) = &self.esdf_window {
            c.esdf.window = Some([w[0], w[1], w[2]]);
        }
        c.check()?;
        Ok(c)
    }
}

/// Bytes from "256M", "2G", "512K" (binary multiples), a plain number, or "unlimited"
/// (`None`).
pub fn parse_bytes(s: &str) -> Result<Option<u64>> {
    let t = s.trim();
    if t.eq_ignore_ascii_case("unlimited") || t.is_empty() {
        return Ok(None);
    }
    let (num, mult) = match t.char_indices().last() {
        Some((i, c)) if c.is_ascii_alphabetic() => {
            let m: u64 = match c.to_ascii_uppercase() {
                'K' => 1 << 10,
                'M' => 1 << 20,
                'G' => 1 << 30,
                'T' => 1 << 40,
                _ => bail!("memory_budget '{s}': the suffix must be K, M, G or T"),
            };
            (&t[..i], m)
        }
        _ => (t, 1),
    };
    let n: u64 = num
        .trim()
        .parse()
        .with_context(|| format!("memory_budget '{s}': not a whole number of bytes"))?;
    let bytes = n
        .checked_mul(mult)
        .with_context(|| format!("memory_budget '{s}' is too large"))?;
    if bytes < 1 << 20 {
        bail!("memory_budget '{s}' is below 1M: a map needs more");
    }
    Ok(Some(bytes))
}

/// Apply a (possibly partial) TOML document over `base`: keys it names replace base's.
fn merge_toml(base: &Config, text: &str) -> Result<Config> {
    let mut doc = toml::Table::try_from(base)?;
    let over: toml::Table = toml::from_str(text)?;
    for (k, v) in over {
        match (doc.get_mut(&k), v) {
            (Some(toml::Value::Table(t)), toml::Value::Table(o)) => t.extend(o),
            (Some(slot), v) => *slot = v,
            (None, _) => bail!("unknown setting '{k}'"),
        }
    }
    Ok(doc.try_into()?)
}

impl Config {
    pub fn ray_mode(&self) -> RayMode {
        match self.mode {
            Mode::Exact => RayMode::Exact,
            Mode::Subsample => RayMode::Subsample {
                factor: self.subsample_factor,
            },
            Mode::Bundle => RayMode::Bundle {
                threshold: self.bundle_threshold,
            },
            Mode::UniqueEnd => RayMode::UniqueEnd,
        }
    }

    pub fn threads(&self) -> usize {
        match self.threads {
            0 => std::thread::available_parallelism().map_or(1, |n| n.get()),
            n => n,
        }
    }

    pub fn check(&self) -> Result<()> {
        if !(1..=FRAME_SUBSCRIBER_BUFFER).contains(&self.queue_depth) {
            bail!("queue_depth must be 1..={FRAME_SUBSCRIBER_BUFFER}");
        }
        if !(0..=99).contains(&self.rt_priority) {
            bail!("rt_priority must be 0..=99");
        }
        if let Err(e) = self.ros2.check() {
            bail!("{e}");
        }
        if !(0.0..=3.6e6).contains(&self.snapshot_interval_ms) {
            bail!("snapshot_interval_ms must be in [0, 3.6e6] (an hour)");
        }
        let voxels = self.max_range / self.resolution;
        if voxels > voxmap_map::integrate::MAX_RANGE_VOXELS {
            bail!(
                "max_range {} m is {voxels:.0} voxels at resolution {} m; at most {} are supported",
                self.max_range,
                self.resolution,
                voxmap_map::integrate::MAX_RANGE_VOXELS
            );
        }
        if !(0.0..=86_400.0).contains(&self.store_save_interval_s) {
            bail!("store_save_interval_s must be in [0, 86400] (a day)");
        }
        let budget = self.memory_budget()?;
        if budget.is_some() && self.store.is_empty() {
            bail!("memory_budget needs a store (--store DIR) to keep what it evicts");
        }
        // The map, integrator and field check the rest with their own messages.
        self.new_map()?;
        self.integrator()?;
        self.field_config().radius(self.resolution)?;
        Ok(())
    }

    pub fn new_map(&self) -> Result<OccupancyMap> {
        Ok(OccupancyMap::new(self.resolution, self.sensor_model)?)
    }

    /// The distance field's settings (whether or not it is enabled).
    pub fn field_config(&self) -> FieldConfig {
        FieldConfig {
            max_distance: self.esdf.max_distance,
            unknown: self.esdf.unknown,
            window: self.esdf.window,
        }
    }

    pub fn integrator_config(&self) -> IntegratorConfig {
        IntegratorConfig {
            threads: self.threads(),
            max_range: self.max_range,
            mode: self.ray_mode(),
            pin_threads: self.pin_threads,
        }
    }

    pub fn integrator(&self) -> Result<Integrator> {
        Ok(Integrator::new(self.integrator_config())?)
    }

    /// The map, integrator and distance field these settings describe.
    pub fn mapper_config(&self) -> MapperConfig {
        MapperConfig {
            resolution: self.resolution,
            model: self.sensor_model,
            integrator: self.integrator_config(),
            field: self.esdf.enabled.then(|| self.field_config()),
        }
    }

    /// `memory_budget` in bytes (`None`: unlimited).
    pub fn memory_budget(&self) -> Result<Option<u64>> {
        parse_bytes(&self.memory_budget)
    }

    /// The tile store these settings ask for, if any.
    pub fn store_config(&self) -> Result<Option<StoreConfig>> {
        if self.store.is_empty() {
            return Ok(None);
        }
        let dir = PathBuf::from(&self.store);
        Ok(Some(StoreConfig {
            resume: voxmap_map::store::exists(&dir),
            dir,
            memory_budget: self.memory_budget()?,
        }))
    }

    /// A mapper with an empty map, or with the map of its tile store (loaded as frames
    /// reach it).
    pub fn mapper(&self) -> Result<Mapper> {
        let mut m = Mapper::new(&self.mapper_config())?;
        if let Some(sc) = self.store_config()? {
            m.open_store(&sc)
                .with_context(|| format!("tile store {}", sc.dir.display()))?;
        }
        Ok(m)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn defaults_file_then_flags() {
        let c = MappingArgs::default().resolve().unwrap();
        assert_eq!(c.resolution, 0.1);
        assert_eq!(c.sensor_model, SensorModel::default());
        assert_eq!(c.ray_mode(), RayMode::Exact);
        let dir = std::env::temp_dir().join(format!("voxmap-config-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let f = dir.join("c.toml");
        std::fs::write(
            &f,
            "resolution = 0.05\nmode = \"bundle\"\n[sensor_model]\np_hit = 0.8\n",
        )
        .unwrap();
        let a = MappingArgs {
            config: Some(f.clone()),
            resolution: Some(0.2),
            ..Default::default()
        };
        let c = a.resolve().unwrap();
        assert_eq!(c.resolution, 0.2, "flag beats file");
        assert_eq!(c.sensor_model.p_hit, 0.8, "file beats default");
        assert_eq!(c.sensor_model.p_miss, 0.4, "untouched keys keep defaults");
        assert_eq!(c.ray_mode(), RayMode::Bundle { threshold: 8 });
        for (bad, why) in [
            ("resolutoin = 0.1\n", "unknown setting"),
            ("resolution = -1.0\n", "resolution"),
            ("mode = \"fast\"\n", "unknown variant `fast`"),
            ("intake = \"all\"\n", "unknown variant `all`"),
            ("[sensor_model]\np_hit = 0.3\n", "p_hit"),
            ("resolution = \"x\"\n", "invalid type"),
            ("max_range = 1000.0\n", "8192"),
            ("[sensor_model]\np_hitt = 0.9\n", "unknown field"),
            ("snapshot_interval_ms = 1e23\n", "snapshot_interval_ms"),
            ("[esdf]\nmax_distance = 9.0\n", "esdf max_distance"),
            ("[esdf]\nunknown = \"maybe\"\n", "unknown variant `maybe`"),
            ("[esdf]\nwindow = [1.0, -1.0, 1.0]\n", "esdf window"),
            ("memory_budget = \"256X\"\n", "suffix"),
            ("memory_budget = \"12\"\n", "below 1M"),
            ("memory_budget = \"99999999999T\"\n", "too large"),
            ("memory_budget = \"256M\"\n", "needs a store"),
        ] {
            std::fs::write(&f, bad).unwrap();
            let e = format!(
                "{:#}",
                MappingArgs {
                    config: Some(f.clone()),
                    ..Default::default()
                }
                .resolve()
                .unwrap_err()
            );
            assert!(e.contains(why), "{bad}: {e}");
        }
        std::fs::remove_dir_all(&dir).unwrap();
    }
}

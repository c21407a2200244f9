//! The service's counters: for the periodic log line and the `stats` control request.

use crate::quantile::percentile;
use voxmap_ipc::StatsWire;
use voxmap_map::Mapper;

/// Counters for the periodic log line and the `stats` request.
#[derive(Default, Debug)]
pub(super) struct Stats {
    pub received: u64,
    pub integrated: u64,
    pub dropped: u64,
    pub rejected: u64,
    /// Rejected frames by reason (`FrameRejected::kind`, `IntegrateError::kind`).
    pub rejected_by: std::collections::BTreeMap<&'static str, u64>,
    pub points: u64,
    pub skipped_points: u64,
    /// Integration times (ms) of the last frames, oldest first.
    pub integrate_ms: std::collections::VecDeque<f64>,
    /// Distance field update times (ms) of the last frames, with `[esdf] enabled`.
    pub esdf_ms: std::collections::VecDeque<f64>,
    /// Send-to-receive times (us) of the last time-stamped frames.
    pub intake_us: std::collections::VecDeque<f64>,
    pub last_snapshot_bytes: usize,
    pub last_encode_ms: f64,
    pub sequence: u64,
    pub publish_failures: u64,
    /// The integrator's kernel name.
    pub kernel: &'static str,
    /// When the last log line was made, with the tile evictions and loads then: the line
    /// gives their rates since.
    pub tiles_logged: Option<(std::time::Instant, u64, u64)>,
}

impl Stats {
    pub(super) fn record(window: &mut std::collections::VecDeque<f64>, x: f64) {
        if window.len() == 1024 {
            window.pop_front();
        }
        window.push_back(x);
    }

    pub(super) fn wire(&self, mapper: &Mapper) -> StatsWire {
        let map = mapper.map();
        let tiles = mapper.tile_stats().unwrap_or_default();
        let sorted = |w: &std::collections::VecDeque<f64>| {
            let mut t: Vec<f64> = w.iter().copied().collect();
            t.sort_by(f64::total_cmp);
            t
        };
        let (t, intake) = (sorted(&self.integrate_ms), sorted(&self.intake_us));
        StatsWire {
            frames_received: self.received,
            frames_integrated: self.integrated,
            frames_dropped: self.dropped,
            frames_rejected: self.rejected,
            points_integrated: self.points,
            points_skipped: self.skipped_points,
            map_leaves: map.grid().leaf_count() as u64,
            map_memory_bytes: map.memory_bytes() as u64,
            snapshot_bytes: self.last_snapshot_bytes as u64,
            snapshot_sequence: self.sequence,
            integrate_ms_p50: percentile(&t, 0.5),
            integrate_ms_p99: percentile(&t, 0.99),
            integrate_ms_max: t.last().copied().unwrap_or(0.0),
            encode_ms_last: self.last_encode_ms,
            intake_us_p50: percentile(&intake, 0.5),
            intake_us_p99: percentile(&intake, 0.99),
            kernel: StatsWire::kernel_field(self.kernel),
            memory_budget_bytes: tiles.memory_budget.unwrap_or(0),
            resident_bytes: if mapper.tile_stats().is_some() {
                tiles.resident_bytes
            } else {
                map.grid().live_bytes() as u64
            },
            tiles_resident: tiles.tiles_resident,
            tiles_stored: tiles.tiles_stored,
            tile_evictions: tiles.evictions,
            tile_loads: tiles.loads,
            tiles_refused: tiles.refused,
            tile_wait_ms_max: tiles.worst_wait.as_secs_f64() * 1e3,
        }
    }

    pub(super) fn log_line(&mut self, mapper: &Mapper) -> String {
        let w = self.wire(mapper);
        let by: Vec<String> = self
            .rejected_by
            .iter()
            .map(|(k, n)| format!("{k} {n}"))
            .collect();
        let by = if by.is_empty() {
            String::new()
        } else {
            format!(" ({})", by.join(", "))
        };
        let esdf = if self.esdf_ms.is_empty() {
            String::new()
        } else {
            let mut t: Vec<f64> = self.esdf_ms.iter().copied().collect();
            t.sort_by(f64::total_cmp);
            format!(
                "; distance field ms p50 {:.2} p99 {:.2}",
                percentile(&t, 0.5),
                percentile(&t, 0.99)
            )
        };
        let now = std::time::Instant::now();
        let store = match mapper.tile_stats() {
            None => String::new(),
            Some(t) => {
                let (ev_s, ld_s) = match self.tiles_logged {
                    Some((at, ev, ld)) => {
                        let dt = now.duration_since(at).as_secs_f64().max(1e-3);
                        ((t.evictions - ev) as f64 / dt, (t.loads - ld) as f64 / dt)
                    }
                    None => (0.0, 0.0),
                };
                self.tiles_logged = Some((now, t.evictions, t.loads));
                format!("; {t} (evicted {ev_s:.1}/s, loaded {ld_s:.1}/s)")
            }
        };
        format!(
            "frames received {} integrated {} dropped {} rejected {}{by}; points {} (skipped {}); integrate ms p50 {:.2} p99 {:.2}{esdf}; \
             snapshot {} bytes, encode {:.2} ms, {} not published; map {} leaves, {} bytes{store}",
            w.frames_received, w.frames_integrated, w.frames_dropped, w.frames_rejected, w.points_integrated, w.points_skipped,
            w.integrate_ms_p50, w.integrate_ms_p99, w.snapshot_bytes, w.encode_ms_last, self.publish_failures, w.map_leaves, w.map_memory_bytes
        )
    }
}

//! Snapshots out: the map encoded straight into a loaned shared-memory sample, stamped,
//! sent, and the planners woken.

use super::MapState;
use crate::os::now_ns;
use anyhow::{anyhow, Result};
use iceoryx2::port::notifier::Notifier;
use iceoryx2::port::publisher::Publisher;
use iceoryx2::port::update_connections::UpdateConnections;
use iceoryx2::prelude::*;
use std::time::Instant;
use voxmap_ipc::{SnapshotHeader, SNAPSHOT_WIRE_VERSION};
use voxmap_map::snapshot::Meta;

/// The snapshot publisher and its wake-up.
pub(super) struct SnapshotOut {
    pub publisher: Publisher<ipc::Service, [u8], SnapshotHeader>,
    pub notifier: Notifier<ipc::Service>,
    /// Include per-voxel log-odds.
    pub with_values: bool,
}

impl SnapshotOut {
    /// Publish the map as it is now. A snapshot that cannot be published (no shared memory
    /// left, a map too large for one snapshot) is logged and counted; the service keeps
    /// integrating.
    pub fn publish(&self, s: &mut MapState) {
        if let Err(e) = self.try_publish(s) {
            s.stats.publish_failures += 1;
            eprintln!(
                "voxmap serve: snapshot {} not published: {e:#}",
                s.sequence()
            );
        }
    }

    fn try_publish(&self, s: &mut MapState) -> Result<()> {
        let t = Instant::now();
        let meta = Meta {
            sequence: s.sequence(),
            timestamp_ns: s.stamp_ns(),
            with_values: self.with_values,
        };
        let scope = s.snapshot_scope();
        let plan = s.mapper.snapshot(scope, meta);
        let n = plan.encoded_len();
        let mut sample = self
            .publisher
            .loan_slice(n)
            .map_err(|e| anyhow!(e).context(format!("loaning {n} bytes for a snapshot")))?;
        let payload = sample.payload_mut();
        s.mapper.write_snapshot(&plan, payload)?;
        *sample.user_header_mut() = SnapshotHeader {
            version: SNAPSHOT_WIRE_VERSION,
            reserved: 0,
            sequence: s.sequence(),
            len: n as u64,
            published_ns: now_ns(),
        };
        sample
            .send()
            .map_err(|e| anyhow!(e).context("sending a snapshot"))?;
        self.notifier
            .notify()
            .map_err(|e| anyhow!(e).context("waking the planners"))?;
        s.stats.last_snapshot_bytes = n;
        s.stats.sequence = s.sequence();
        s.stats.last_encode_ms = t.elapsed().as_secs_f64() * 1e3;
        Ok(())
    }

    /// Hand the history sample to planners that joined since (iceoryx2 delivers it only
    /// when the publisher sends or updates its connections).
    pub fn update_connections(&self) {
        let _ = self.publisher.update_connections();
    }
}

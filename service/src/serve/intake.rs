//! Frames in: received under the intake policy (latest wins, or a queue), validated, and
//! integrated; rejections and drops counted.

use super::stats::Stats;
use super::MapState;
use crate::config::Intake;
use crate::os::now_ns;
use anyhow::{anyhow, Result};
use iceoryx2::identifiers::UniquePublisherId;
use iceoryx2::port::subscriber::Subscriber;
use iceoryx2::prelude::*;
use iceoryx2::sample::Sample;
use std::collections::HashMap;
use voxmap_ipc::FrameHeader;
use voxmap_map::{Frame, FrameStamp};

type FrameSample = Sample<ipc::Service, [[f32; 3]], FrameHeader>;

/// The frame subscriber and what the policy needs to remember.
pub(super) struct FrameIntake {
    pub subscriber: Subscriber<ipc::Service, [[f32; 3]], FrameHeader>,
    pub policy: Intake,
    /// Last sequence seen per publisher, to count frames the queue dropped.
    last_seq: HashMap<UniquePublisherId, u64>,
}

impl FrameIntake {
    pub fn new(
        subscriber: Subscriber<ipc::Service, [[f32; 3]], FrameHeader>,
        policy: Intake,
    ) -> Self {
        Self {
            subscriber,
            policy,
            last_seq: HashMap::new(),
        }
    }

    /// Integrate what is waiting: under `Latest` the newest frame, under `Queue` every
    /// waiting frame in order. Returns whether any frame was integrated.
    pub fn integrate_waiting(&mut self, s: &mut MapState) -> Result<bool> {
        let mut any = false;
        while let Some(sample) = self.next(s)? {
            any |= integrate(sample, s);
            if self.policy == Intake::Latest {
                break;
            }
        }
        Ok(any)
    }

    /// The next frame to integrate. Latest wins: take everything waiting, keep the newest.
    /// Queue: one at a time, in order; the subscriber's buffer of `queue_depth` drops the
    /// oldest on overflow, which shows as a gap in a publisher's sequence.
    fn next(&mut self, s: &mut MapState) -> Result<Option<FrameSample>> {
        let queue = self.policy == Intake::Queue;
        let mut next = None;
        while let Some(sample) = self
            .subscriber
            .receive()
            .map_err(|e| anyhow!(e).context("receiving a frame"))?
        {
            let stats = &mut s.stats;
            stats.received += 1;
            let h = sample.user_header();
            if h.timestamp_ns != 0 {
                let us = now_ns().saturating_sub(h.timestamp_ns) as f64 / 1e3;
                Stats::record(&mut stats.intake_us, us);
            }
            let seq = h.sequence;
            // Only frames that pass validation count for gaps: garbage headers would make
            // `dropped` mean nothing (their sequence numbers are random).
            let valid = h.validate(sample.payload().len()).is_ok();
            let last = match valid {
                true => self.last_seq.insert(sample.header().publisher_id(), seq),
                false => None,
            };
            if let Some(prev) = last {
                // The sequence is the publisher's word: no arithmetic on it may overflow.
                if queue && seq > prev.saturating_add(1) {
                    stats.dropped = stats.dropped.saturating_add(seq - prev - 1);
                }
            }
            if next.replace(sample).is_some() {
                stats.dropped += 1;
            }
            if queue {
                break;
            }
        }
        Ok(next)
    }
}

/// Validate and integrate one frame; a bad frame is logged and counted, and changes
/// nothing. Returns whether it was integrated.
fn integrate(sample: FrameSample, s: &mut MapState) -> bool {
    let h = *sample.user_header();
    let outcome = h
        .validate(sample.payload().len())
        .map_err(|e| (e.kind(), e.to_string()))
        .and_then(|pose| {
            let frame = Frame {
                pose,
                points: sample.payload(),
            };
            let stamp = FrameStamp {
                sequence: h.sequence,
                stamp_ns: if h.timestamp_ns != 0 {
                    h.timestamp_ns
                } else {
                    now_ns()
                },
            };
            s.mapper
                .insert(&frame, stamp)
                .map_err(|e| (e.kind(), e.to_string()))
        });
    drop(sample);
    let stats = &mut s.stats;
    match outcome {
        Err((kind, why)) => {
            stats.rejected += 1;
            *stats.rejected_by.entry(kind).or_default() += 1;
            // The first few one by one, then every 1000th: a publisher sending garbage
            // must not flood the log (the counters have every one).
            if stats.rejected <= 5 || stats.rejected.is_multiple_of(1000) {
                eprintln!(
                    "voxmap serve: frame {} rejected: {why} ({} rejected so far)",
                    h.sequence, stats.rejected
                );
            }
            false
        }
        Ok(rep) => {
            let (tiles, field, rep) = (rep.tiles, rep.field, rep.integrate);
            stats.integrated += 1;
            stats.points += rep.points;
            stats.skipped_points += rep.skipped_nonfinite;
            // A frame's time includes the tiles it waited for and the evictions after it.
            let mut ms = rep.times.total().as_secs_f64() * 1e3;
            if let Some(t) = tiles {
                ms += (t.load_time + t.evict_time).as_secs_f64() * 1e3;
                for e in &t.refused {
                    eprintln!("voxmap serve: tile store: {e}; its region reads as unknown");
                }
                if let Some(e) = &t.write_error {
                    eprintln!(
                        "voxmap serve: tile store: {e}; no tile is evicted until it is fixed"
                    );
                }
            }
            Stats::record(&mut stats.integrate_ms, ms);
            if let Some(r) = field {
                Stats::record(&mut stats.esdf_ms, r.time.as_secs_f64() * 1e3);
            }
            true
        }
    }
}

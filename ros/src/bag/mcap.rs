//! MCAP storage files: topics from the summary section (or a scan when there is none),
//! messages by a streaming read of the data section with chunk CRCs checked before use.

use super::{BagError, Message, TopicInfo};
use mcap::records::{op, Record};
use mcap::sans_io::linear_reader::{LinearReadEvent, LinearReader, LinearReaderOptions};
use mcap::sans_io::summary_reader::{SummaryReadEvent, SummaryReader};
use std::collections::HashMap;
use std::io::{Read, Seek};
use std::ops::ControlFlow;
use std::path::Path;

/// Largest record (or decompressed chunk) read: 1 GiB, beyond any real sensor message, so
/// that a lying length cannot ask for an absurd buffer.
const RECORD_LIMIT: usize = 1 << 30;

struct Channel {
    topic: String,
    type_name: String,
    wanted: bool,
}

/// What [`stream`] calls with each wanted message: its channel, log time and bytes.
type OnMessage<'a> = dyn FnMut(&Channel, u64, &[u8]) -> ControlFlow<()> + 'a;

fn open(path: &Path) -> Result<(std::fs::File, u64), BagError> {
    let io = |source| BagError::Io {
        path: path.into(),
        source,
    };
    let f = std::fs::File::open(path).map_err(io)?;
    let len = f.metadata().map_err(io)?.len();
    Ok((f, len))
}

/// Stream every wanted message of the file to `on_message`. Stops at the first damage,
/// with the offset read up to.
fn stream(
    path: &Path,
    wanted: &dyn Fn(&str) -> bool,
    on_message: &mut OnMessage<'_>,
) -> Result<(), BagError> {
    let (mut file, len) = open(path)?;
    let opts = LinearReaderOptions::default()
        .with_prevalidate_chunk_crcs(true)
        .with_record_length_limit(RECORD_LIMIT);
    let mut reader = LinearReader::new_with_options(opts);
    let mut fed = 0u64;
    let mut schemas: HashMap<u16, String> = HashMap::new();
    let mut channels: HashMap<u16, Channel> = HashMap::new();
    let damaged = |offset: u64, source| BagError::Mcap {
        path: path.into(),
        offset,
        len,
        source,
    };
    while let Some(event) = reader.next_event() {
        match event.map_err(|e| damaged(fed, e))? {
            LinearReadEvent::ReadRequest(n) => {
                let buf = reader.insert(n);
                let k = file.read(buf).map_err(|source| BagError::Io {
                    path: path.into(),
                    source,
                })?;
                fed += k as u64;
                reader.notify_read(k);
            }
            LinearReadEvent::Record { opcode, data } => {
                if !matches!(opcode, op::SCHEMA | op::CHANNEL | op::MESSAGE) {
                    continue;
                }
                match mcap::parse_record(opcode, data).map_err(|e| damaged(fed, e))? {
                    Record::Schema { header, .. } => {
                        schemas.insert(header.id, header.name);
                    }
                    Record::Channel(c) => {
                        let type_name = schemas.get(&c.schema_id).cloned().unwrap_or_default();
                        // rosbag2 writes CDR; a channel in any other encoding is not ROS 2 data.
                        let ok = c.message_encoding == "cdr";
                        channels.insert(
                            c.id,
                            Channel {
                                wanted: ok && wanted(&c.topic),
                                topic: c.topic,
                                type_name,
                            },
                        );
                    }
                    Record::Message { header, data } => {
                        let Some(c) = channels.get(&header.channel_id) else {
                            return Err(damaged(
                                fed,
                                mcap::McapError::UnknownChannel(header.sequence, header.channel_id),
                            ));
                        };
                        if c.wanted && on_message(c, header.log_time, &data).is_break() {
                            return Ok(());
                        }
                    }
                    _ => {}
                }
            }
        }
    }
    Ok(())
}

pub(super) fn read(
    path: &Path,
    wanted: &dyn Fn(&str) -> bool,
    f: &mut dyn FnMut(Message<'_>) -> ControlFlow<()>,
) -> Result<(), BagError> {
    stream(path, wanted, &mut |c, log_time_ns, data| {
        f(Message {
            topic: &c.topic,
            type_name: &c.type_name,
            log_time_ns,
            data,
        })
    })
}

/// The file's topics and time span: from its summary section, else by reading it through
/// (a damaged file yields the topics before the damage).
pub(super) fn topics(path: &Path) -> Result<super::Topics, BagError> {
    if let Some(s) = summary(path)? {
        let mut topics: Vec<TopicInfo> = s
            .channels
            .values()
            .map(|c| TopicInfo {
                name: c.topic.clone(),
                type_name: c
                    .schema
                    .as_ref()
                    .map(|s| s.name.clone())
                    .unwrap_or_default(),
                encoding: c.message_encoding.clone(),
                count: s
                    .stats
                    .as_ref()
                    .map(|st| st.channel_message_counts.get(&c.id).copied().unwrap_or(0)),
            })
            .collect();
        topics.sort_by(|a, b| a.name.cmp(&b.name));
        let span = s
            .stats
            .as_ref()
            .filter(|st| st.message_count > 0)
            .map(|st| (st.message_start_time, st.message_end_time));
        return Ok((topics, span));
    }
    let mut by_name: Vec<TopicInfo> = Vec::new();
    let mut span: Option<(u64, u64)> = None;
    let scan = stream(path, &|_| true, &mut |c, t, _| {
        match by_name.iter_mut().find(|x| x.name == c.topic) {
            Some(x) => x.count = x.count.map(|n| n + 1),
            None => by_name.push(TopicInfo {
                name: c.topic.clone(),
                type_name: c.type_name.clone(),
                encoding: "cdr".into(),
                count: Some(1),
            }),
        }
        span = Some(span.map_or((t, t), |(a, b)| (a.min(t), b.max(t))));
        ControlFlow::Continue(())
    });
    match scan {
        // Topics up to the damage; reading the messages will report it.
        Ok(()) | Err(BagError::Mcap { .. }) => Ok((by_name, span)),
        Err(e) => Err(e),
    }
}

/// The summary section, or `None` if the file has none or it cannot be read.
fn summary(path: &Path) -> Result<Option<mcap::Summary>, BagError> {
    let (mut file, _) = open(path)?;
    let mut r = SummaryReader::new();
    while let Some(event) = r.next_event() {
        let Ok(event) = event else { return Ok(None) };
        let step = match event {
            SummaryReadEvent::ReadRequest(n) => file.read(r.insert(n)).map(|k| r.notify_read(k)),
            SummaryReadEvent::SeekRequest(to) => file.seek(to).map(|p| r.notify_seeked(p)),
        };
        if step.is_err() {
            return Ok(None);
        }
    }
    Ok(r.finish())
}

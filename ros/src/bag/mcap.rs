//! MCAP storage files: topics from the summary section (or a scan when there is none),
//! messages by a streaming read of the data section with chunk CRCs checked before use.

use super::{BagError, Message, TopicInfo};
use mcap::records::{op, Record};
use mcap::sans_io::linear_reader::{LinearReadEvent, LinearReader, LinearReaderOptions};
use std::collections::HashMap;
use std::io::{Read, Seek, SeekFrom};
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

/// The records of the data section (and of its chunks) voxmap reads: schema and channel
/// names, and each wanted message handed on.
struct Records<'w, 'm> {
    wanted: &'w dyn Fn(&str) -> bool,
    on_message: &'w mut OnMessage<'m>,
    schemas: HashMap<u16, String>,
    channels: HashMap<u16, Channel>,
}

impl Records<'_, '_> {
    /// Take one record; `Break` once the callback asked to stop.
    fn take(&mut self, opcode: u8, data: &[u8]) -> Result<ControlFlow<()>, Damage> {
        if !matches!(opcode, op::SCHEMA | op::CHANNEL | op::MESSAGE) {
            return Ok(ControlFlow::Continue(()));
        }
        if !lengths_fit(opcode, data) {
            return Err(Damage::Unchecked("a field is longer than its record"));
        }
        match mcap::parse_record(opcode, data)? {
            Record::Schema { header, .. } => {
                self.schemas.insert(header.id, header.name);
            }
            Record::Channel(c) => {
                let type_name = self.schemas.get(&c.schema_id).cloned().unwrap_or_default();
                // rosbag2 writes CDR; a channel in any other encoding is not ROS 2 data.
                let ok = c.message_encoding == "cdr";
                self.channels.insert(
                    c.id,
                    Channel {
                        wanted: ok && (self.wanted)(&c.topic),
                        topic: c.topic,
                        type_name,
                    },
                );
            }
            Record::Message { header, data } => {
                let Some(c) = self.channels.get(&header.channel_id) else {
                    return Err(mcap::McapError::UnknownChannel(
                        header.sequence,
                        header.channel_id,
                    )
                    .into());
                };
                if c.wanted {
                    return Ok((self.on_message)(c, header.log_time, &data));
                }
            }
            _ => {}
        }
        Ok(ControlFlow::Continue(()))
    }
}

/// Why a record or chunk is refused, before the file offset is known.
enum Damage {
    Mcap(mcap::McapError),
    Unchecked(&'static str),
}

impl From<mcap::McapError> for Damage {
    fn from(e: mcap::McapError) -> Self {
        Self::Mcap(e)
    }
}

/// The records of a chunk: decompressed into `buf` (reused between chunks) if compressed,
/// checked against the chunk's size and CRC. Chunks are read here rather than by the
/// `mcap` reader: mcap 0.26 subtracts a record's length from an uncompressed chunk's without
/// a check (sans_io/linear_reader.rs:745), which panics under overflow checks and, without
/// them, reads on past the chunk (found by fuzzing, regression tests in `bag`).
fn chunk_records<'a>(data: &'a [u8], buf: &'a mut Vec<u8>) -> Result<&'a [u8], Damage> {
    if !lengths_fit(op::CHUNK, data) {
        return Err(Damage::Unchecked("a field is longer than its record"));
    }
    let Record::Chunk { header, .. } = mcap::parse_record(op::CHUNK, data)? else {
        return Err(Damage::Unchecked("a chunk that does not parse as one"));
    };
    // The compressed records follow the fixed fields, the compression string and their
    // u64 length; `parse_record` has checked that they fit.
    let start = 28 + 4 + header.compression.len() + 8;
    let data = usize::try_from(header.compressed_size)
        .ok()
        .and_then(|n| data.get(start..start.checked_add(n)?))
        .ok_or(Damage::Unchecked(
            "a chunk's records are longer than the chunk",
        ))?;
    let size = header.uncompressed_size;
    if size > RECORD_LIMIT as u64 {
        return Err(mcap::McapError::ChunkTooLarge(size).into());
    }
    // Decompressed as a stream, so that the buffer grows with what the data holds, not
    // with what a lying header claims.
    let decompress = |d: std::io::Result<Box<dyn Read + '_>>, buf: &mut Vec<u8>| {
        buf.clear();
        d.and_then(|d| d.take(size + 1).read_to_end(buf))
            .map_err(mcap::McapError::from)
    };
    let records: &[u8] = match header.compression.as_str() {
        "" => data,
        "zstd" => {
            decompress(
                zstd::Decoder::with_buffer(data).map(|d| Box::new(d) as _),
                buf,
            )?;
            buf
        }
        "lz4" => {
            decompress(lz4::Decoder::new(data).map(|d| Box::new(d) as _), buf)?;
            buf
        }
        other => return Err(mcap::McapError::UnsupportedCompression(other.into()).into()),
    };
    if records.len() as u64 != size {
        return Err(Damage::Unchecked(
            "a chunk's records are not its stated size",
        ));
    }
    let saved = header.uncompressed_crc;
    if saved != 0 {
        let calculated = crc32fast::hash(records);
        if calculated != saved {
            return Err(mcap::McapError::BadChunkCrc { saved, calculated }.into());
        }
    }
    Ok(records)
}

/// Each record of a chunk's records in turn to `records`, each body within the chunk.
fn each_record(mut rest: &[u8], records: &mut Records) -> Result<ControlFlow<()>, Damage> {
    while let Some((&[opcode], tail)) = rest.split_first_chunk::<1>() {
        let Some((len, tail)) = tail.split_first_chunk::<8>() else {
            return Err(mcap::McapError::UnexpectedEoc.into());
        };
        let body = usize::try_from(u64::from_le_bytes(*len))
            .ok()
            .and_then(|n| tail.get(..n))
            .ok_or(Damage::Unchecked("a record is longer than its chunk"))?;
        if records.take(opcode, body)?.is_break() {
            return Ok(ControlFlow::Break(()));
        }
        rest = &tail[body.len()..];
    }
    Ok(ControlFlow::Continue(()))
}

/// Stream every wanted message of the file to `on_message`. Stops at the first damage,
/// with the offset read up to.
fn stream(
    path: &Path,
    wanted: &dyn Fn(&str) -> bool,
    on_message: &mut OnMessage<'_>,
) -> Result<(), BagError> {
    let (mut file, len) = open(path)?;
    // No record is longer than the file: the reader reserves a record's stated length
    // before it reads it, which a small file with a lying length otherwise inflates to
    // the limit.
    let opts = LinearReaderOptions::default()
        .with_emit_chunks(true)
        .with_record_length_limit(RECORD_LIMIT.min(usize::try_from(len).unwrap_or(usize::MAX)));
    let mut reader = LinearReader::new_with_options(opts);
    let mut fed = 0u64;
    let mut records = Records {
        wanted,
        on_message,
        schemas: HashMap::new(),
        channels: HashMap::new(),
    };
    let mut chunk = Vec::new();
    let damaged = |offset: u64, d: Damage| match d {
        Damage::Mcap(source) => BagError::Mcap {
            path: path.into(),
            offset,
            len,
            source,
        },
        Damage::Unchecked(why) => BagError::McapUnchecked {
            path: path.into(),
            offset,
            len,
            why,
        },
    };
    while let Some(event) = reader.next_event() {
        let taken = match event.map_err(|e| damaged(fed, e.into()))? {
            LinearReadEvent::ReadRequest(n) => {
                let buf = reader.insert(n);
                let k = file.read(buf).map_err(|source| BagError::Io {
                    path: path.into(),
                    source,
                })?;
                fed += k as u64;
                reader.notify_read(k);
                continue;
            }
            LinearReadEvent::Record {
                opcode: op::CHUNK,
                data,
            } => chunk_records(data, &mut chunk).and_then(|r| each_record(r, &mut records)),
            LinearReadEvent::Record { opcode, data } => records.take(opcode, data),
        };
        if taken.map_err(|d| damaged(fed, d))?.is_break() {
            return Ok(());
        }
    }
    Ok(())
}

/// Whether every length-prefixed field of a Schema, Channel or Chunk record fits in the
/// record. mcap 0.26 allocates a string's declared length before it reads it (binrw's
/// `reserve_exact`): a 5 KB file could ask for 4 GB (found by fuzzing). Messages are not
/// checked here: their data is a borrowed slice.
fn lengths_fit(opcode: u8, data: &[u8]) -> bool {
    // Skip `n` fixed bytes, then each u32-prefixed field in turn.
    fn fields(data: &[u8], fixed: usize, prefixed: usize) -> Option<&[u8]> {
        let mut rest = data.get(fixed..)?;
        for _ in 0..prefixed {
            let (len, tail) = rest.split_first_chunk::<4>()?;
            rest = tail.get(u32::from_le_bytes(*len) as usize..)?;
        }
        Some(rest)
    }
    match opcode {
        // id, then name, encoding and data.
        op::SCHEMA => fields(data, 2, 3).is_some(),
        // id and schema id, then topic, message encoding and the metadata map, whose
        // entries (key and value strings) must fit in the map's byte length.
        op::CHANNEL => {
            let Some(map) = fields(data, 4, 2).and_then(|r| {
                let (len, tail) = r.split_first_chunk::<4>()?;
                tail.get(..u32::from_le_bytes(*len) as usize)
            }) else {
                return false;
            };
            let mut rest = map;
            while !rest.is_empty() {
                match fields(rest, 0, 2) {
                    Some(r) => rest = r,
                    None => return false,
                }
            }
            true
        }
        // start and end time, uncompressed size and CRC, then the compression.
        op::CHUNK => fields(data, 28, 1).is_some(),
        _ => true,
    }
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
    if let Some(t) = summary(path)? {
        return Ok(t);
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
        Ok(()) | Err(BagError::Mcap { .. } | BagError::McapUnchecked { .. }) => Ok((by_name, span)),
        Err(e) => Err(e),
    }
}

/// Largest summary section read: 256 MiB (chunk and message indexes of a very long bag).
const SUMMARY_LIMIT: u64 = 1 << 28;

/// Topics (with message counts) and time span from the summary section, or `None` if the
/// file has none or it cannot be read. The section's records go through the same length
/// guard as the data section's ([`lengths_fit`]); mcap's own `SummaryReader` parses them
/// unguarded (a 5 KB file asked it for 3 GB, found by fuzzing).
fn summary(path: &Path) -> Result<Option<super::Topics>, BagError> {
    let (mut file, len) = open(path)?;
    // The footer record (opcode, length 20, summary start, summary offset start, CRC)
    // and the end magic.
    const TAIL: u64 = 1 + 8 + 20 + 8;
    if len < 8 + TAIL {
        return Ok(None);
    }
    let mut tail = [0u8; TAIL as usize];
    let read_tail = file
        .seek(SeekFrom::End(-(TAIL as i64)))
        .and_then(|_| file.read_exact(&mut tail));
    if read_tail.is_err() || tail[0] != op::FOOTER || tail[29..] != mcap::MAGIC[..] {
        return Ok(None);
    }
    let Ok(Record::Footer(footer)) = mcap::parse_record(op::FOOTER, &tail[9..29]) else {
        return Ok(None);
    };
    let start = footer.summary_start;
    if start == 0 || start < 8 || start > len - TAIL || len - start > SUMMARY_LIMIT {
        return Ok(None);
    }
    let mut section = Vec::new();
    let read = file
        .seek(SeekFrom::Start(start))
        .and_then(|_| (&mut file).take(len - start).read_to_end(&mut section));
    if read.is_err() {
        return Ok(None);
    }
    // Chunks do not belong in the summary: emitted whole and skipped, never entered.
    let opts = LinearReaderOptions::default()
        .with_skip_start_magic(true)
        .with_emit_chunks(true)
        .with_record_length_limit(RECORD_LIMIT.min(section.len()));
    let mut reader = LinearReader::new_with_options(opts);
    let mut fed = 0;
    let mut schemas: HashMap<u16, String> = HashMap::new();
    let mut channels: Vec<(u16, String, String, u16)> = Vec::new();
    let mut stats = None;
    while let Some(event) = reader.next_event() {
        let Ok(event) = event else { return Ok(None) };
        match event {
            LinearReadEvent::ReadRequest(n) => {
                let k = n.min(section.len() - fed);
                reader.insert(k).copy_from_slice(&section[fed..fed + k]);
                fed += k;
                reader.notify_read(k);
            }
            LinearReadEvent::Record { opcode, data } => {
                if !matches!(opcode, op::SCHEMA | op::CHANNEL | op::STATISTICS) {
                    continue;
                }
                if !lengths_fit(opcode, data) {
                    return Ok(None);
                }
                match mcap::parse_record(opcode, data) {
                    Ok(Record::Schema { header, .. }) => {
                        schemas.insert(header.id, header.name);
                    }
                    Ok(Record::Channel(c)) => {
                        channels.push((c.id, c.topic, c.message_encoding, c.schema_id))
                    }
                    Ok(Record::Statistics(st)) => stats = Some(st),
                    Ok(_) => {}
                    Err(_) => return Ok(None),
                }
            }
        }
    }
    let mut topics: Vec<TopicInfo> = channels
        .into_iter()
        .map(|(id, name, encoding, schema)| TopicInfo {
            name,
            type_name: schemas.get(&schema).cloned().unwrap_or_default(),
            encoding,
            count: stats.as_ref().map(|st: &mcap::records::Statistics| {
                st.channel_message_counts.get(&id).copied().unwrap_or(0)
            }),
        })
        .collect();
    topics.sort_by(|a, b| a.name.cmp(&b.name));
    let span = stats
        .filter(|st| st.message_count > 0)
        .map(|st| (st.message_start_time, st.message_end_time));
    Ok(Some((topics, span)))
}

//! rosbag2 bags: a directory with `metadata.yaml` and its storage files, or one `.mcap` or
//! `.db3` file. [`Bag::open`] finds the files and the topics; [`Bag::read_file`] streams a
//! file's messages, in recording order, to a callback with the serialized bytes borrowed.

mod mcap;
mod metadata;
mod sqlite;

use std::ops::ControlFlow;
use std::path::{Path, PathBuf};

/// rosbag2's two storage plugins.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Storage {
    /// MCAP (rosbag2's default since Iron), chunks uncompressed, zstd or lz4.
    Mcap,
    /// SQLite 3 (`.db3`, the default before).
    Sqlite3,
}

impl std::fmt::Display for Storage {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Self::Mcap => "mcap",
            Self::Sqlite3 => "sqlite3",
        })
    }
}

/// A topic of the bag.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct TopicInfo {
    pub name: String,
    /// `pkg/msg/Type`.
    pub type_name: String,
    /// The serialization (`cdr` for every ROS 2 bag voxmap reads).
    pub encoding: String,
    /// Messages, when the bag's summary or metadata says.
    pub count: Option<u64>,
}

/// One message, borrowed from the reader for the length of the callback.
#[derive(Debug, Clone, Copy)]
pub struct Message<'a> {
    pub topic: &'a str,
    pub type_name: &'a str,
    /// When the recorder received it (nanoseconds since the epoch).
    pub log_time_ns: u64,
    /// The serialized message: the CDR encapsulation header, then CDR.
    pub data: &'a [u8],
}

/// Why a bag cannot be opened or read any further. Each names the file.
#[derive(Debug)]
pub enum BagError {
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
    /// Not a rosbag2 directory, `.mcap` or `.db3` file.
    NotABag { path: PathBuf, why: String },
    /// `metadata.yaml` cannot be read as rosbag2 metadata.
    Metadata { path: PathBuf, why: String },
    /// A bag voxmap does not read (file- or message-level compression, another storage).
    Unsupported { path: PathBuf, why: String },
    /// The MCAP reader stopped: a truncated or damaged file. `offset` is how far into the
    /// file it had read.
    Mcap {
        path: PathBuf,
        offset: u64,
        len: u64,
        source: ::mcap::McapError,
    },
    /// Damage the MCAP reader does not check for itself, found before it sees the bytes: a
    /// field longer than its record, a record longer than its chunk.
    McapUnchecked {
        path: PathBuf,
        offset: u64,
        len: u64,
        why: &'static str,
    },
    /// SQLite refused the file or a query on it.
    Sqlite {
        path: PathBuf,
        source: rusqlite::Error,
    },
}

impl std::fmt::Display for BagError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Io { path, .. } => write!(f, "{}: cannot read", path.display()),
            Self::NotABag { path, why } => write!(f, "{}: not a ROS 2 bag: {why}", path.display()),
            Self::Metadata { path, why } => {
                write!(f, "{}: bad rosbag2 metadata: {why}", path.display())
            }
            Self::Unsupported { path, why } => write!(f, "{}: {why}", path.display()),
            Self::Mcap {
                path, offset, len, ..
            } => write!(
                f,
                "{}: MCAP damaged at byte {offset} of {len} (truncated or corrupt)",
                path.display()
            ),
            Self::McapUnchecked {
                path,
                offset,
                len,
                why,
            } => write!(
                f,
                "{}: MCAP damaged at byte {offset} of {len} ({why})",
                path.display()
            ),
            Self::Sqlite { path, .. } => write!(f, "{}: SQLite bag unreadable", path.display()),
        }
    }
}

impl std::error::Error for BagError {
    fn source(&self) -> Option<&(dyn std::error::Error + 'static)> {
        match self {
            Self::Io { source, .. } => Some(source),
            Self::Mcap { source, .. } => Some(source),
            Self::Sqlite { source, .. } => Some(source),
            _ => None,
        }
    }
}

/// A storage file of a bag.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct BagFile {
    pub path: PathBuf,
    pub storage: Storage,
}

/// An opened bag: its files and topics. Reading is by [`Bag::read_file`].
#[derive(Debug, Clone)]
pub struct Bag {
    pub path: PathBuf,
    pub files: Vec<BagFile>,
    pub topics: Vec<TopicInfo>,
    /// First and last log time (ns), when the summary or metadata says.
    pub span_ns: Option<(u64, u64)>,
}

/// True if `path` looks like a bag: a directory with `metadata.yaml` or with `.mcap` or
/// `.db3` files, or such a file.
pub fn is_bag(path: &Path) -> bool {
    if path.is_dir() {
        return path.join("metadata.yaml").is_file() || !storage_files(path).is_empty();
    }
    storage_of(path).is_some()
}

fn storage_of(path: &Path) -> Option<Storage> {
    match path.extension()?.to_str()? {
        "mcap" => Some(Storage::Mcap),
        "db3" => Some(Storage::Sqlite3),
        _ => None,
    }
}

fn storage_files(dir: &Path) -> Vec<BagFile> {
    let mut v: Vec<BagFile> = std::fs::read_dir(dir)
        .into_iter()
        .flatten()
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter_map(|path| storage_of(&path).map(|storage| BagFile { path, storage }))
        .collect();
    // rosbag2 names split files <bag>_0, <bag>_1, ...: order by that number, then name.
    v.sort_by_key(|f| (split_index(&f.path), f.path.clone()));
    v
}

fn split_index(p: &Path) -> u64 {
    p.file_stem()
        .and_then(|s| s.to_str())
        .and_then(|s| s.rsplit('_').next())
        .and_then(|n| n.parse().ok())
        .unwrap_or(0)
}

impl Bag {
    /// Open a bag directory or a single storage file, and learn its topics: from
    /// `metadata.yaml`, else the MCAP summary or the SQLite tables (a damaged MCAP without
    /// a summary is scanned up to the damage).
    pub fn open(path: &Path) -> Result<Self, BagError> {
        let io = |source| BagError::Io {
            path: path.into(),
            source,
        };
        if !path.is_dir() {
            let storage = storage_of(path).ok_or_else(|| BagError::NotABag {
                path: path.into(),
                why: "expected a rosbag2 directory, a .mcap or a .db3 file".into(),
            })?;
            std::fs::metadata(path).map_err(io)?;
            let files = vec![BagFile {
                path: path.into(),
                storage,
            }];
            let (topics, span_ns) = topics_of(&files)?;
            return Ok(Self {
                path: path.into(),
                files,
                topics,
                span_ns,
            });
        }
        let meta_path = path.join("metadata.yaml");
        if !meta_path.is_file() {
            let files = storage_files(path);
            if files.is_empty() {
                return Err(BagError::NotABag {
                    path: path.into(),
                    why: "no metadata.yaml and no .mcap or .db3 file".into(),
                });
            }
            let (topics, span_ns) = topics_of(&files)?;
            return Ok(Self {
                path: path.into(),
                files,
                topics,
                span_ns,
            });
        }
        let text = std::fs::read_to_string(&meta_path).map_err(|source| BagError::Io {
            path: meta_path.clone(),
            source,
        })?;
        let bad = |why: String| BagError::Metadata {
            path: meta_path.clone(),
            why,
        };
        let m = metadata::parse(&text).map_err(bad)?;
        let storage = match m.storage_identifier.as_str() {
            "mcap" => Storage::Mcap,
            "sqlite3" => Storage::Sqlite3,
            s => {
                return Err(BagError::Unsupported {
                    path: path.into(),
                    why: format!("storage '{s}' (voxmap reads mcap and sqlite3)"),
                })
            }
        };
        if !matches!(
            m.compression_mode.to_ascii_lowercase().as_str(),
            "" | "none"
        ) {
            return Err(BagError::Unsupported {
                path: path.into(),
                why: format!(
                    "{} compression by {} (decompress it with `ros2 bag convert` or record with \
                     MCAP chunk compression instead)",
                    m.compression_mode.to_ascii_lowercase(),
                    m.compression_format
                ),
            });
        }
        if m.relative_file_paths.is_empty() {
            return Err(bad(format!(
                "version {}: no relative_file_paths",
                m.version
            )));
        }
        let mut files = Vec::new();
        for rel in &m.relative_file_paths {
            if Path::new(rel).is_absolute() || rel.split('/').any(|c| c == "..") {
                return Err(bad(format!("file path '{rel}' leaves the bag directory")));
            }
            let p = path.join(rel);
            std::fs::metadata(&p).map_err(|source| BagError::Io {
                path: p.clone(),
                source,
            })?;
            files.push(BagFile { path: p, storage });
        }
        let topics = m
            .topics_with_message_count
            .iter()
            .map(|t| TopicInfo {
                name: t.topic_metadata.name.clone(),
                type_name: t.topic_metadata.type_name.clone(),
                encoding: t.topic_metadata.serialization_format.clone(),
                count: Some(t.message_count),
            })
            .collect();
        let span_ns = match (m.starting_time, m.duration) {
            (Some(s), Some(d)) if s.nanoseconds_since_epoch >= 0 && d.nanoseconds >= 0 => Some((
                s.nanoseconds_since_epoch as u64,
                (s.nanoseconds_since_epoch as u64).saturating_add(d.nanoseconds as u64),
            )),
            _ => None,
        };
        Ok(Self {
            path: path.into(),
            files,
            topics,
            span_ns,
        })
    }

    /// The topics of type `type_name`.
    pub fn topics_of_type<'a>(&'a self, type_name: &'a str) -> impl Iterator<Item = &'a TopicInfo> {
        self.topics.iter().filter(move |t| t.type_name == type_name)
    }

    /// Stream the messages of file `index` whose topic `wanted` accepts, in recording order,
    /// to `f`, until the file ends, `f` breaks, or the file turns out damaged (the error
    /// comes after every message before the damage).
    pub fn read_file(
        &self,
        index: usize,
        wanted: &dyn Fn(&str) -> bool,
        f: &mut dyn FnMut(Message<'_>) -> ControlFlow<()>,
    ) -> Result<(), BagError> {
        let Some(file) = self.files.get(index) else {
            return Ok(());
        };
        match file.storage {
            Storage::Mcap => mcap::read(&file.path, wanted, f),
            Storage::Sqlite3 => sqlite::read(&file.path, wanted, f),
        }
    }
}

type Topics = (Vec<TopicInfo>, Option<(u64, u64)>);

/// Topics of bag files without metadata, merged over the files.
fn topics_of(files: &[BagFile]) -> Result<Topics, BagError> {
    let mut all: Vec<TopicInfo> = Vec::new();
    let mut span: Option<(u64, u64)> = None;
    for f in files {
        let (topics, s) = match f.storage {
            Storage::Mcap => mcap::topics(&f.path)?,
            Storage::Sqlite3 => sqlite::topics(&f.path)?,
        };
        for t in topics {
            match all.iter_mut().find(|a| a.name == t.name) {
                Some(a) => {
                    a.count = match (a.count, t.count) {
                        // Counts too large to add are a summary's lie: unknown.
                        (Some(x), Some(y)) => x.checked_add(y),
                        _ => None,
                    }
                }
                None => all.push(t),
            }
        }
        if let Some((a, b)) = s {
            span = Some(span.map_or((a, b), |(x, y)| (x.min(a), y.max(b))));
        }
    }
    Ok((all, span))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn dir(name: &str) -> PathBuf {
        let d = std::env::temp_dir().join(format!("voxmap_ros_{name}_{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&d);
        std::fs::create_dir_all(&d).unwrap();
        d
    }

    fn metadata(extra: &str, files: &str) -> String {
        format!(
            "rosbag2_bagfile_information:\n  version: 9\n  storage_identifier: mcap\n  \
             relative_file_paths:\n{files}  topics_with_message_count: []\n{extra}"
        )
    }

    #[test]
    fn bags_voxmap_cannot_read_say_why() {
        let d = dir("meta");
        assert!(matches!(Bag::open(&d), Err(BagError::NotABag { .. })));
        std::fs::write(d.join("x_0.mcap"), b"").unwrap();
        let m = |extra: &str, files: &str| {
            std::fs::write(d.join("metadata.yaml"), metadata(extra, files)).unwrap();
            Bag::open(&d).unwrap_err().to_string()
        };
        let e = m(
            "  compression_mode: FILE\n  compression_format: zstd\n",
            "    - x_0.mcap\n",
        );
        assert!(e.contains("file compression by zstd"), "{e}");
        let e = m("", "    - ../../etc/passwd\n");
        assert!(e.contains("leaves the bag directory"), "{e}");
        let e = m("", "    - missing.mcap\n");
        assert!(e.contains("missing.mcap: cannot read"), "{e}");
        std::fs::write(d.join("metadata.yaml"), "rosbag2_bagfile_information: 3\n").unwrap();
        assert!(matches!(Bag::open(&d), Err(BagError::Metadata { .. })));
        std::fs::remove_dir_all(&d).unwrap();
    }

    #[test]
    fn garbage_storage_files_are_errors_not_panics() {
        let d = dir("garbage");
        let db3 = d.join("x.db3");
        std::fs::write(&db3, vec![0x5a; 5000]).unwrap();
        assert!(matches!(Bag::open(&db3), Err(BagError::Sqlite { .. })));
        let mcap = d.join("x.mcap");
        std::fs::write(&mcap, vec![0x5a; 5000]).unwrap();
        // No summary and no readable record: no topics; reading names the damage.
        let bag = Bag::open(&mcap).unwrap();
        assert!(bag.topics.is_empty());
        let e = bag
            .read_file(0, &|_| true, &mut |_| ControlFlow::Continue(()))
            .unwrap_err();
        assert!(
            e.to_string().contains("x.mcap: MCAP damaged at byte"),
            "{e}"
        );
        std::fs::remove_dir_all(&d).unwrap();
    }

    /// Open `ros/testdata/<name>` and read all of its first file.
    fn read_testdata(name: &str) -> Result<(), BagError> {
        let p = Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("testdata")
            .join(name);
        Bag::open(&p)?.read_file(0, &|_| true, &mut |_| ControlFlow::Continue(()))
    }

    /// Found by fuzzing (target `bag_file`, the second by CI's run): an uncompressed chunk
    /// whose record is longer than the chunk. The mcap reader's unchecked subtraction
    /// panicked there under overflow checks (the fuzzer aborts on any panic, caught or
    /// not); voxmap now reads chunks itself, and refuses it.
    #[test]
    fn a_record_longer_than_its_chunk_is_damage() {
        for name in [
            "mcap_chunk_length_overflow.mcap",
            "mcap_record_longer_than_uncompressed_chunk.mcap",
        ] {
            let e = read_testdata(name).unwrap_err().to_string();
            assert!(e.contains("MCAP damaged at byte"), "{name}: {e}");
        }
    }

    /// A one-chunk MCAP file of three messages, written by the `mcap` crate with
    /// `compression`; returns the file and the offset of its chunk record's body.
    fn chunked(compression: Option<::mcap::Compression>) -> (Vec<u8>, usize) {
        let mut out = std::io::Cursor::new(Vec::new());
        let mut w = ::mcap::WriteOptions::new()
            .compression(compression)
            .create(&mut out)
            .unwrap();
        let schema = w
            .add_schema("std_msgs/msg/String", "ros2msg", b"string data")
            .unwrap();
        let ch = w
            .add_channel(schema, "/chatter", "cdr", &Default::default())
            .unwrap();
        for i in 0..3u32 {
            let header = ::mcap::records::MessageHeader {
                channel_id: ch,
                sequence: i,
                log_time: u64::from(i),
                publish_time: u64::from(i),
            };
            w.write_to_known_channel(&header, &[0, 1, 0, 0, 2, 0, 0, 0, b'a' + i as u8, 0])
                .unwrap();
        }
        w.finish().unwrap();
        drop(w);
        let bytes = out.into_inner();
        // Top-level records after the magic: opcode, u64 length, body.
        let mut at = 8;
        while bytes[at] != ::mcap::records::op::CHUNK {
            at += 9 + u64::from_le_bytes(bytes[at + 1..at + 9].try_into().unwrap()) as usize;
        }
        (bytes, at + 9)
    }

    fn read_bytes(name: &str, bytes: &[u8]) -> Result<Vec<u8>, BagError> {
        let d = dir(name);
        std::fs::create_dir_all(&d).unwrap();
        let p = d.join("x.mcap");
        std::fs::write(&p, bytes).unwrap();
        let mut got = Vec::new();
        let r = Bag::open(&p).and_then(|b| {
            b.read_file(0, &|_| true, &mut |m| {
                got.push(m.data[8]);
                ControlFlow::Continue(())
            })
        });
        std::fs::remove_dir_all(&d).unwrap();
        r.map(|()| got)
    }

    /// Chunks in each compression are read; a chunk whose size, CRC or compression lies is
    /// damage, found before any of its records is used.
    #[test]
    fn chunks_are_checked_before_their_records_are_read() {
        use ::mcap::Compression::{Lz4, Zstd};
        for c in [None, Some(Zstd), Some(Lz4)] {
            let (bytes, chunk) = chunked(c);
            assert_eq!(read_bytes("chunk_ok", &bytes).unwrap(), b"abc", "{c:?}");
            // The uncompressed size (body bytes 16..24) claimed 2^29: refused, and without
            // a buffer of that size (the records are decompressed as a stream).
            let mut lying = bytes.clone();
            lying[chunk + 16..chunk + 24].copy_from_slice(&(1u64 << 29).to_le_bytes());
            let e = read_bytes("chunk_size", &lying).unwrap_err().to_string();
            assert!(e.contains("MCAP damaged"), "{c:?}: {e}");
            // The CRC (body bytes 24..28) off by one.
            let mut crc = bytes.clone();
            crc[chunk + 24] ^= 1;
            let e = read_bytes("chunk_crc", &crc).unwrap_err();
            assert!(
                matches!(
                    &e,
                    BagError::Mcap {
                        source: ::mcap::McapError::BadChunkCrc { .. },
                        ..
                    }
                ),
                "{c:?}: {e}"
            );
        }
        // A compression voxmap does not know ("zstd" spelt "zstx").
        let (mut bytes, chunk) = chunked(Some(Zstd));
        bytes[chunk + 32 + 3] = b'x';
        let e = read_bytes("chunk_kind", &bytes).unwrap_err();
        assert!(
            matches!(
                &e,
                BagError::Mcap {
                    source: ::mcap::McapError::UnsupportedCompression(_),
                    ..
                }
            ),
            "{e}"
        );
    }

    /// Found by fuzzing: a Channel record whose topic string claims 4 GB. Refused before
    /// the mcap crate would reserve that much.
    #[test]
    fn a_string_longer_than_its_record_is_damage() {
        let e = read_testdata("mcap_string_length_4gb.mcap")
            .unwrap_err()
            .to_string();
        assert!(e.contains("MCAP damaged at byte"), "{e}");
    }

    /// Found by the `bag_file` fuzz target running at 400 inputs a second with 1.2 GB
    /// resident: a record whose length claims more than the file holds made the reader
    /// reserve that length (up to its 1 GiB limit) before finding the file's end. No record
    /// may now be longer than its file: refused at once.
    #[test]
    fn a_record_longer_than_its_file_is_refused_before_anything_is_reserved() {
        let d = dir("long_record");
        let mut bytes = ::mcap::MAGIC.to_vec();
        bytes.push(0x01); // a Header record
        bytes.extend_from_slice(&(1u64 << 29).to_le_bytes());
        bytes.extend_from_slice(&[0; 16]);
        let path = d.join("x.mcap");
        std::fs::write(&path, &bytes).unwrap();
        let e = Bag::open(&path)
            .and_then(|b| b.read_file(0, &|_| true, &mut |_| ControlFlow::Continue(())))
            .unwrap_err();
        assert!(
            matches!(
                e,
                BagError::Mcap {
                    source: ::mcap::McapError::RecordTooLarge { len, .. },
                    ..
                } if len == 1 << 29
            ),
            "{e:?}"
        );
        std::fs::remove_dir_all(&d).unwrap();
    }

    /// Found by fuzzing (`bag_file`, 3.2 M runs in): a summary whose two channels of one
    /// topic claim message counts that overflow when added. The count is unknown, not a
    /// panic (overflow checks) or a wrapped number (without them).
    #[test]
    fn topic_counts_too_large_to_add_are_unknown() {
        let p = Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("testdata")
            .join("mcap_topic_counts_overflow.mcap");
        let bag = Bag::open(&p).unwrap();
        let unknown: Vec<_> = (bag.topics.iter())
            .filter(|t| t.count.is_none())
            .map(|t| t.name.as_str())
            .collect();
        assert!(!unknown.is_empty(), "{:?}", bag.topics);
    }

    #[test]
    fn split_files_are_read_in_rosbag2_order() {
        let d = dir("split");
        for n in ["b_10.mcap", "b_2.mcap", "b_0.mcap", "b_1.db3"] {
            std::fs::write(d.join(n), b"").unwrap();
        }
        let names: Vec<_> = storage_files(&d)
            .iter()
            .map(|f| f.path.file_name().unwrap().to_string_lossy().into_owned())
            .collect();
        assert_eq!(names, ["b_0.mcap", "b_1.db3", "b_2.mcap", "b_10.mcap"]);
        std::fs::remove_dir_all(&d).unwrap();
    }
}

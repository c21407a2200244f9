//! Compact, pointer-free occupancy snapshots and the zero-copy [`SnapshotView`].
//!
//! A snapshot is one contiguous little-endian buffer (the tree linearized, NanoVDB-style):
//! a fixed [`layout::Header`], an open-addressing table of blocks (64^3 voxels) and which
//! of their leaves exist, per-leaf known and occupied masks (`record`), optionally the
//! per-voxel log-odds, and optionally a distance field section (`field`). [`Encoder`]
//! sizes a snapshot of a list of leaves and writes it straight into a caller's buffer (the
//! map crate's `snapshot::Plan` drives it over a map, on its thread pool);
//! [`SnapshotView::open`] validates every offset and count once, after which every query
//! is bounds-safe and never panics, whatever the bytes. See `docs/snapshot-format.md`.

pub mod encode;
pub mod field;
pub mod layout;
pub mod record;
pub mod view;

pub use encode::{Encoder, FieldBands, InOrder, MapInfo, Meta, Pieces, PlannedLeaf, Scope};
pub use field::{FieldView, Nearest};
pub use layout::{EncodeError, Header, SnapshotError, FORMAT_VERSION, MAGIC};
pub use view::{InvalidBox, InvalidSegment, SnapshotView};

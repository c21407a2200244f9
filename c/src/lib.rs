//! voxmap-c: the C API of voxmap (`include/voxmap.h`, generated from this crate by cbindgen;
//! `include/voxmap.hpp` is the C++ layer over it).
//!
//! - [`field`]: the distance field of a view, when its snapshot carries one.
//! - [`view`]: `voxmap_view`, a validated snapshot read in place (from a file, from a
//!   caller's bytes, or from shared memory), with the planner's queries.
//! - [`subscriber`]: `voxmap_subscriber`, the newest snapshot of a running service.
//! - [`publisher`]: `voxmap_publisher`, frames loaned in shared memory and sent.
//! - [`control`]: `voxmap_control`, the service's stats, save, load and clear.
//! - [`error`]: status codes, `voxmap_last_error`, and the guard that keeps every failure
//!   (a null or bad argument, a Rust panic) on this side of the boundary.
//!
//! Every function accepts null and bad arguments: it returns an error code (or null, or
//! `VOXMAP_STATE_ERROR`) and says why in `voxmap_last_error()`; nothing panics across the
//! boundary. Thread safety is stated per type.

// The C names are the API (fixed by the header), not Rust's.
#![allow(non_camel_case_types)]

pub mod control;
pub mod error;
pub mod field;
pub mod publisher;
pub mod subscriber;
pub mod view;

pub use error::voxmap_last_error;

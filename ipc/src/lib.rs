//! voxmap-ipc: the process boundary between `voxmap serve` and its clients, in one place
//! so that the two sides cannot drift apart.
//!
//! - [`wire`]: the `#[repr(C)]` headers of frame and snapshot samples, their versions and
//!   the frame's validation ([`FrameHeader::validate`]).
//! - [`control`]: the control protocol: [`ControlKind`], [`MapScope`], the request and
//!   response payloads.
//! - [`names`]: the iceoryx2 service names of one map ([`ServiceNames`]).
//! - [`ports`]: the node and the services with their QoS ([`ports::qos`]), opened the same
//!   way by both sides, and [`OpenError`].
//!
//! Service names under prefix `p` and map `m`: `p/m/frames` (+ `/event`), `p/m/snapshot`
//! (+ `/event`), `p/m/control`.

pub mod control;
pub mod names;
pub mod ports;
pub mod wire;

pub use control::{
    ControlError, ControlKind, ControlRequest, ControlResponse, MapScope, StatsWire,
    CONTROL_MESSAGE_MAX, CONTROL_PATH_MAX,
};
pub use names::ServiceNames;
pub use ports::OpenError;
pub use wire::{
    FrameHeader, FrameRejected, SnapshotHeader, FRAME_VERSION, MAX_FRAME_POINTS,
    SNAPSHOT_WIRE_VERSION,
};

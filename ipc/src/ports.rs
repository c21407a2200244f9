//! The iceoryx2 node and services of one map, opened the same way by the service and its
//! clients: one function per service, with the QoS both sides must agree on ([`qos`]).

use crate::control::{ControlRequest, ControlResponse};
use crate::names::ServiceNames;
use crate::wire::{FrameHeader, SnapshotHeader};
use iceoryx2::node::NodeCreationFailure;
use iceoryx2::prelude::*;
use iceoryx2::service::builder::event::EventOpenOrCreateError;
use iceoryx2::service::builder::publish_subscribe::PublishSubscribeOpenOrCreateError;
use iceoryx2::service::builder::request_response::RequestResponseOpenOrCreateError;
use iceoryx2::service::port_factory::{event, publish_subscribe, request_response};
use iceoryx2::service::service_name::ServiceNameError;

/// Service-level settings both sides must agree on (when creating; minimums when opening).
pub mod qos {
    /// Frames a service's subscriber buffers; older ones are overwritten (safe overflow).
    pub const FRAME_SUBSCRIBER_BUFFER: usize = 4;
    pub const MAX_FRAME_PUBLISHERS: usize = 16;
    pub const MAX_SNAPSHOT_SUBSCRIBERS: usize = 16;
    /// Snapshots one planner may hold at once.
    pub const SNAPSHOT_BORROWED: usize = 2;
    pub const MAX_NODES: usize = 64;
}

/// The frames service: `[[f32; 3]]` points with a [`FrameHeader`].
pub type FramesService = publish_subscribe::PortFactory<ipc::Service, [[f32; 3]], FrameHeader>;
/// The snapshot service: snapshot bytes with a [`SnapshotHeader`].
pub type SnapshotService = publish_subscribe::PortFactory<ipc::Service, [u8], SnapshotHeader>;
/// An event service (wake-ups for frames and snapshots).
pub type EventService = event::PortFactory<ipc::Service>;
/// The control service.
pub type ControlService =
    request_response::PortFactory<ipc::Service, ControlRequest, (), ControlResponse, ()>;

/// Why a node or service could not be opened; iceoryx2's own error is the source.
#[derive(Debug)]
#[non_exhaustive]
pub enum OpenError {
    /// iceoryx2 does not accept this node name.
    NodeName {
        name: String,
        source: SemanticStringError,
    },
    /// iceoryx2 does not accept this service name.
    ServiceName {
        name: String,
        source: ServiceNameError,
    },
    /// Creating the node failed.
    Node(NodeCreationFailure),
    /// Opening or creating a publish-subscribe service failed (wrong types or QoS of an
    /// existing service, or no resources).
    PublishSubscribe {
        service: String,
        source: PublishSubscribeOpenOrCreateError,
    },
    /// Opening or creating an event service failed.
    Event {
        service: String,
        source: EventOpenOrCreateError,
    },
    /// Opening or creating the control service failed.
    RequestResponse {
        service: String,
        source: RequestResponseOpenOrCreateError,
    },
}

impl std::fmt::Display for OpenError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::NodeName { name, .. } => write!(f, "iceoryx2 refuses the node name {name:?}"),
            Self::ServiceName { name, .. } => {
                write!(f, "iceoryx2 refuses the service name {name:?}")
            }
            Self::Node(_) => write!(f, "creating the iceoryx2 node failed"),
            Self::PublishSubscribe { service, .. }
            | Self::Event { service, .. }
            | Self::RequestResponse { service, .. } => {
                write!(f, "opening iceoryx2 service {service:?} failed")
            }
        }
    }
}

impl std::error::Error for OpenError {
    fn source(&self) -> Option<&(dyn std::error::Error + 'static)> {
        match self {
            Self::NodeName { source, .. } => Some(source),
            Self::ServiceName { source, .. } => Some(source),
            Self::Node(e) => Some(e),
            Self::PublishSubscribe { source, .. } => Some(source),
            Self::Event { source, .. } => Some(source),
            Self::RequestResponse { source, .. } => Some(source),
        }
    }
}

/// A node named `name` with the default iceoryx2 config; `signals` says whether it takes
/// SIGINT/SIGTERM (the service) or leaves them to the process (clients).
pub fn node(name: &str, signals: SignalHandlingMode) -> Result<Node<ipc::Service>, OpenError> {
    let node_name = NodeName::new(name).map_err(|source| OpenError::NodeName {
        name: name.into(),
        source,
    })?;
    NodeBuilder::new()
        .name(&node_name)
        .config(&Config::default())
        .signal_handling_mode(signals)
        .create::<ipc::Service>()
        .map_err(OpenError::Node)
}

fn service_name(s: &str) -> Result<ServiceName, OpenError> {
    s.try_into().map_err(|source| OpenError::ServiceName {
        name: s.into(),
        source,
    })
}

/// The frames service (shared by publishers and the service).
pub fn open_frames(
    node: &Node<ipc::Service>,
    names: &ServiceNames,
) -> Result<FramesService, OpenError> {
    node.service_builder(&service_name(&names.frames)?)
        .publish_subscribe::<[[f32; 3]]>()
        .user_header::<FrameHeader>()
        .subscriber_max_buffer_size(qos::FRAME_SUBSCRIBER_BUFFER)
        .history_size(0)
        .max_publishers(qos::MAX_FRAME_PUBLISHERS)
        .max_nodes(qos::MAX_NODES)
        .enable_safe_overflow(true)
        .open_or_create()
        .map_err(|source| OpenError::PublishSubscribe {
            service: names.frames.clone(),
            source,
        })
}

/// The snapshot service: history 1, so that a late planner gets the current snapshot.
pub fn open_snapshots(
    node: &Node<ipc::Service>,
    names: &ServiceNames,
) -> Result<SnapshotService, OpenError> {
    node.service_builder(&service_name(&names.snapshot)?)
        .publish_subscribe::<[u8]>()
        .user_header::<SnapshotHeader>()
        .history_size(1)
        .subscriber_max_buffer_size(2)
        .subscriber_max_borrowed_samples(qos::SNAPSHOT_BORROWED)
        .max_subscribers(qos::MAX_SNAPSHOT_SUBSCRIBERS)
        .max_publishers(1)
        .max_nodes(qos::MAX_NODES)
        .enable_safe_overflow(true)
        .open_or_create()
        .map_err(|source| OpenError::PublishSubscribe {
            service: names.snapshot.clone(),
            source,
        })
}

/// An event service by name (`names.frames_event` or `names.snapshot_event`).
pub fn open_event(node: &Node<ipc::Service>, name: &str) -> Result<EventService, OpenError> {
    node.service_builder(&service_name(name)?)
        .event()
        .max_nodes(qos::MAX_NODES)
        .open_or_create()
        .map_err(|source| OpenError::Event {
            service: name.into(),
            source,
        })
}

/// The control service.
pub fn open_control(
    node: &Node<ipc::Service>,
    names: &ServiceNames,
) -> Result<ControlService, OpenError> {
    node.service_builder(&service_name(&names.control)?)
        .request_response::<ControlRequest, ControlResponse>()
        .max_nodes(qos::MAX_NODES)
        .open_or_create()
        .map_err(|source| OpenError::RequestResponse {
            service: names.control.clone(),
            source,
        })
}

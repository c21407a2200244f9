//! The iceoryx2 service names of one map.

/// iceoryx2 service names of one map under a prefix.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ServiceNames {
    pub frames: String,
    pub frames_event: String,
    pub snapshot: String,
    pub snapshot_event: String,
    pub control: String,
}

impl ServiceNames {
    /// `<prefix>/<map>/frames` and friends.
    pub fn new(prefix: &str, map: &str) -> Self {
        let base = format!("{prefix}/{map}");
        Self {
            frames: format!("{base}/frames"),
            frames_event: format!("{base}/frames/event"),
            snapshot: format!("{base}/snapshot"),
            snapshot_event: format!("{base}/snapshot/event"),
            control: format!("{base}/control"),
        }
    }
}

//! rosbag2's `metadata.yaml`: which storage files a bag directory holds, in which storage,
//! and its topics with their types and message counts.

use serde::Deserialize;

#[derive(Debug, Deserialize)]
pub(super) struct MetadataFile {
    pub rosbag2_bagfile_information: Metadata,
}

#[derive(Debug, Deserialize)]
pub(super) struct Metadata {
    pub version: u32,
    pub storage_identifier: String,
    #[serde(default)]
    pub relative_file_paths: Vec<String>,
    #[serde(default)]
    pub topics_with_message_count: Vec<TopicWithCount>,
    #[serde(default)]
    pub compression_mode: String,
    #[serde(default)]
    pub compression_format: String,
    #[serde(default)]
    pub starting_time: Option<StartingTime>,
    #[serde(default)]
    pub duration: Option<Duration>,
}

#[derive(Debug, Deserialize)]
pub(super) struct TopicWithCount {
    pub topic_metadata: TopicMetadata,
    #[serde(default)]
    pub message_count: u64,
}

#[derive(Debug, Deserialize)]
pub(super) struct TopicMetadata {
    pub name: String,
    #[serde(rename = "type")]
    pub type_name: String,
    #[serde(default)]
    pub serialization_format: String,
}

#[derive(Debug, Deserialize)]
pub(super) struct StartingTime {
    pub nanoseconds_since_epoch: i64,
}

#[derive(Debug, Deserialize)]
pub(super) struct Duration {
    pub nanoseconds: i64,
}

pub(super) fn parse(text: &str) -> Result<Metadata, String> {
    serde_norway::from_str::<MetadataFile>(text)
        .map(|m| m.rosbag2_bagfile_information)
        .map_err(|e| e.to_string())
}

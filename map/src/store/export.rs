//! A map file (`.vxm`) of a store's tiles, with or without the tiles a mapper holds in
//! memory, streamed tile by tile so that a map larger than memory exports.

use super::{StoreError, TileStore};
use crate::coord::VoxelCoord;
use crate::io::mapfile::{write_map_streamed, MapFileError};
use crate::occupancy::OccupancyMap;
use std::path::Path;

/// Why an export failed; the output file is as it was.
#[derive(Debug)]
#[non_exhaustive]
pub enum ExportError {
    File(MapFileError),
    Store(StoreError),
}

impl std::fmt::Display for ExportError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::File(e) => write!(f, "{e}"),
            Self::Store(e) => write!(f, "{e}"),
        }
    }
}

impl std::error::Error for ExportError {}

impl From<MapFileError> for ExportError {
    fn from(e: MapFileError) -> Self {
        Self::File(e)
    }
}

impl From<StoreError> for ExportError {
    fn from(e: StoreError) -> Self {
        Self::Store(e)
    }
}

/// Write the map file of `tiles` (tile origins, any order) to `path`; `raw` gives each
/// tile's raw leaf records. Tiles go in block order (by origin z, y, x), so the file equals
/// the one the map encoder writes for the same map. Returns the leaves written.
pub(crate) fn write_tiles(
    path: &Path,
    params_of: &OccupancyMap,
    mut tiles: Vec<VoxelCoord>,
    mut raw: impl FnMut(VoxelCoord) -> Result<Vec<u8>, ExportError>,
) -> Result<u64, ExportError> {
    tiles.sort_unstable_by_key(|k| (k.z, k.y, k.x));
    tiles.dedup();
    write_map_streamed(path, params_of, |put| {
        for &k in &tiles {
            put(&raw(k)?)?;
        }
        Ok::<(), ExportError>(())
    })
}

/// `voxmap export`: the map file of the store in `dir` as committed. Every record is
/// checked; a refused one fails the export, naming its tile. Returns the leaves written.
pub fn export(dir: &Path, path: &Path) -> Result<u64, ExportError> {
    let (mut store, manifest) = TileStore::open_read_only(dir)?;
    let p = manifest.params;
    let params_of = OccupancyMap::new(p.resolution, p.model).map_err(|e| StoreError::Params {
        path: dir.into(),
        problem: format!("map parameters: {e}"),
    })?;
    let tiles = (manifest.tiles.iter())
        .map(|e| VoxelCoord::from_array(e.tile))
        .collect();
    write_tiles(path, &params_of, tiles, |k| {
        Ok(store.get_raw(k)?.unwrap_or_default())
    })
}

//! A map file (`.vxm`) of a store's tiles, with or without the tiles a mapper holds in
//! memory (and its distance field's bands), streamed tile by tile so that a map larger
//! than memory exports.

use super::record::RawTile;
use super::{StoreError, TileStore};
use crate::coord::VoxelCoord;
use crate::io::mapfile::{write_map_streamed, MapFileError, StreamedField};
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
/// tile's raw records. Tiles go in block order (by origin z, y, x), so the file equals the
/// one the map encoder writes for the same map. With `field`, the file carries the bands
/// of the leaves `field.1` keeps (those of the field's window). Returns the leaves written.
pub(crate) fn write_tiles(
    path: &Path,
    params_of: &OccupancyMap,
    field: Option<(StreamedField, &dyn Fn(VoxelCoord) -> bool)>,
    mut tiles: Vec<VoxelCoord>,
    mut raw: impl FnMut(VoxelCoord) -> Result<RawTile, ExportError>,
) -> Result<u64, ExportError> {
    tiles.sort_unstable_by_key(|k| (k.z, k.y, k.x));
    tiles.dedup();
    write_map_streamed(path, params_of, field.map(|f| f.0), |sink| {
        for &k in &tiles {
            let raw = raw(k)?;
            let (leaves, mut bands) = raw.split();
            sink.leaves(leaves)?;
            let Some((_, keep)) = &field else { continue };
            // Records read back were checked whole; a resident tile's are the field's.
            while let Ok(((origin, ..), rest)) = voxmap_reader::mapfile::band_record(bands) {
                if keep(origin) {
                    sink.bands(&bands[..bands.len() - rest.len()], 1)?;
                }
                bands = rest;
            }
        }
        Ok::<(), ExportError>(())
    })
}

/// `voxmap export`: the map file of the store in `dir` as committed, without the distance
/// field (whose window only the mapper knows; a mapper loading the file builds it anew). Every record is
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
    write_tiles(path, &params_of, None, tiles, |k| {
        Ok(store.get_raw(k)?.unwrap_or_default())
    })
}

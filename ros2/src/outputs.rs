//! Snapshot to ROS 2 messages: the occupied voxel centres as a PointCloud2, the map as
//! OctoMap binary data in an `octomap_msgs/msg/Octomap`, and a 2D `OccupancyGrid` over a z
//! range. Each reads the snapshot in place; none changes it.

use serde_bytes::ByteBuf;
use voxmap_client::{SnapshotView, VoxelCoord, WorldPoint};
use voxmap_map::io::octomap::{encode_bt_data, BtError};
use voxmap_map::tree::voxel_at;
use voxmap_ros::cloud::datatype;
use voxmap_ros::msg::{
    Header, MapMetaData, OccupancyGrid, Octomap, PointCloud2, PointField, Pose, Quaternion, Time,
    Vector3,
};

/// A stamp in nanoseconds as `builtin_interfaces/msg/Time` (clamped to its range).
pub fn time_of(ns: u64) -> Time {
    let sec = (ns / 1_000_000_000).min(i32::MAX as u64) as i32;
    Time {
        sec,
        nanosec: (ns % 1_000_000_000) as u32,
    }
}

/// The header of every output: the map frame, stamped with the snapshot's data time (the
/// last integrated cloud's stamp).
pub fn header(view: &SnapshotView<'_>, frame: &str) -> Header {
    Header {
        stamp: time_of(view.timestamp_ns()),
        frame_id: frame.to_string(),
    }
}

/// `/voxmap/occupied`: float32 x y z of every occupied voxel's centre, unorganized.
pub fn occupied_cloud(view: &SnapshotView<'_>, frame: &str) -> PointCloud2<ByteBuf> {
    let mut data = Vec::with_capacity(view.counts().1 as usize * 12);
    for p in view.occupied_centers() {
        for c in [p.x, p.y, p.z] {
            data.extend_from_slice(&(c as f32).to_le_bytes());
        }
    }
    let n = (data.len() / 12) as u32;
    let field = |name: &str, offset| PointField {
        name: name.into(),
        offset,
        datatype: datatype::FLOAT32,
        count: 1,
    };
    PointCloud2 {
        header: header(view, frame),
        height: 1,
        width: n,
        fields: vec![field("x", 0), field("y", 4), field("z", 8)],
        is_bigendian: false,
        point_step: 12,
        row_step: 12 * n,
        data: ByteBuf::from(data),
        is_dense: true,
    }
}

/// `/voxmap/octomap_binary`: what `octomap_msgs::binaryMapToMsg` makes of the same map.
pub fn octomap(view: &SnapshotView<'_>, frame: &str) -> Result<Octomap, BtError> {
    let (_, data) = encode_bt_data(view.leaf_occupancy())?;
    Ok(Octomap {
        header: header(view, frame),
        binary: true,
        id: "OcTree".into(),
        resolution: view.resolution(),
        data: ByteBuf::from(data),
    })
}

/// Most cells of one grid (64 Mi: 64 MB of message).
pub const MAX_GRID_CELLS: u64 = 1 << 26;

/// Why no grid was made.
#[derive(Clone, Debug, PartialEq)]
pub enum GridError {
    TooLarge { width: u64, height: u64 },
}

impl std::fmt::Display for GridError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::TooLarge { width, height } => write!(
                f,
                "the map's footprint is {width} x {height} cells, more than {MAX_GRID_CELLS}"
            ),
        }
    }
}

impl std::error::Error for GridError {}

/// `/voxmap/grid`: the column of voxels whose centres lie in `[z_min, z_max]` over each
/// cell: occupied (100) if any is, else free (0) if any is known, else unknown (-1). The
/// grid covers the map's known footprint; cell (0, 0) is its lowest x and y.
pub fn grid(
    view: &SnapshotView<'_>,
    frame: &str,
    z_min: f64,
    z_max: f64,
) -> Result<OccupancyGrid, GridError> {
    let tf = *view.transform();
    let res = view.resolution();
    // Voxel z whose centre (z + 0.5) * res lies in the range.
    let zlo = (z_min / res - 0.5).ceil() as i64;
    let zhi = (z_max / res - 0.5).floor() as i64;
    let (lo, hi) = match view.bounds() {
        Some((lo, hi)) if zlo <= zhi => (lo.to_array(), hi.to_array()),
        _ => ([0; 3], [-1; 3]),
    };
    let width = (i64::from(hi[0]) - i64::from(lo[0]) + 1).max(0) as u64;
    let height = (i64::from(hi[1]) - i64::from(lo[1]) + 1).max(0) as u64;
    if width * height > MAX_GRID_CELLS {
        return Err(GridError::TooLarge { width, height });
    }
    let mut cells = vec![-1i8; (width * height) as usize];
    if !cells.is_empty() {
        for leaf in view.leaf_occupancy() {
            let oz = i64::from(leaf.origin.to_array()[2]);
            if oz + 7 < zlo || oz > zhi {
                continue;
            }
            for i in leaf.known.iter_ones() {
                let v = voxel_at(leaf.origin, i).to_array();
                if !(zlo..=zhi).contains(&i64::from(v[2])) {
                    continue;
                }
                let c = (v[1] - lo[1]) as usize * width as usize + (v[0] - lo[0]) as usize;
                if leaf.occupied.get(i) {
                    cells[c] = 100;
                } else if cells[c] < 0 {
                    cells[c] = 0;
                }
            }
        }
    }
    let corner = if cells.is_empty() {
        WorldPoint::new(0.0, 0.0, 0.0)
    } else {
        tf.voxel_min_corner(VoxelCoord::new(lo[0], lo[1], 0))
    };
    Ok(OccupancyGrid {
        header: header(view, frame),
        info: MapMetaData {
            map_load_time: time_of(view.timestamp_ns()),
            resolution: res as f32,
            width: width as u32,
            height: height as u32,
            origin: Pose {
                translation: Vector3 {
                    x: corner.x,
                    y: corner.y,
                    z: z_min,
                },
                rotation: Quaternion {
                    x: 0.0,
                    y: 0.0,
                    z: 0.0,
                    w: 1.0,
                },
            },
        },
        data: ByteBuf::from(cells.into_iter().map(|c| c as u8).collect::<Vec<u8>>()),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use voxmap_map::io::octomap::encode_bt;
    use voxmap_map::snapshot::{Meta, Plan, Scope};
    use voxmap_map::{Frame, Integrator, IntegratorConfig, OccupancyMap, SensorModel};

    /// A map of one frame: a wall at x = 2 seen from the origin, 0.1 m voxels.
    fn snapshot() -> (OccupancyMap, Vec<u8>) {
        let mut map = OccupancyMap::new(0.1, SensorModel::default()).unwrap();
        let pts: Vec<[f32; 3]> = (0..40)
            .flat_map(|i| (0..20).map(move |j| [2.0, -1.0 + i as f32 * 0.05, j as f32 * 0.1]))
            .collect();
        let mut integ = Integrator::new(IntegratorConfig {
            threads: 1,
            max_range: 10.0,
            ..Default::default()
        })
        .unwrap();
        let frame = Frame {
            pose: nalgebra::Isometry3::identity(),
            points: &pts,
        };
        integ.integrate(&mut map, &frame).unwrap();
        let meta = Meta {
            sequence: 3,
            timestamp_ns: 1_700_000_000_250_000_000,
            with_values: false,
        };
        let plan = Plan::new(&map, Scope::Whole, meta);
        let mut buf = vec![0u8; plan.encoded_len()];
        plan.write(&mut buf).unwrap();
        (map, buf)
    }

    #[test]
    fn the_occupied_cloud_holds_each_occupied_centre_once() {
        let (map, buf) = snapshot();
        let view = SnapshotView::open(&buf).unwrap();
        let c = occupied_cloud(&view, "map");
        assert_eq!(
            (c.header.stamp.sec, c.header.stamp.nanosec),
            (1_700_000_000, 250_000_000)
        );
        let pts = voxmap_ros::cloud::points(&c).unwrap().points;
        let mut want: Vec<[f32; 3]> = view
            .occupied_centers()
            .map(|p| [p.x as f32, p.y as f32, p.z as f32])
            .collect();
        assert_eq!(want.len() as u64, map.counts().occupied);
        assert!(!want.is_empty());
        let key = |p: &[f32; 3]| p.map(|c| (c * 1e4) as i64);
        let mut got = pts.clone();
        got.sort_by_key(key);
        want.sort_by_key(key);
        assert_eq!(got, want);
    }

    #[test]
    fn octomap_data_is_the_bt_file_without_its_header() {
        let (map, buf) = snapshot();
        let view = SnapshotView::open(&buf).unwrap();
        let m = octomap(&view, "map").unwrap();
        let file = encode_bt(map.leaf_occupancy(), 0.1).unwrap();
        assert!(m.binary && m.id == "OcTree" && m.resolution == 0.1);
        assert!(file.ends_with(&m.data));
        let head = std::str::from_utf8(&file[..file.len() - m.data.len()]).unwrap();
        assert!(head.ends_with("data\n"), "{head}");
    }

    #[test]
    fn the_grid_marks_the_wall_occupied_the_floor_free_and_the_rest_unknown() {
        let (_, buf) = snapshot();
        let view = SnapshotView::open(&buf).unwrap();
        let g = grid(&view, "map", 0.05, 1.0).unwrap();
        let (w, h) = (g.info.width as usize, g.info.height as usize);
        assert_eq!(g.data.len(), w * h);
        let at = |x: f64, y: f64| {
            let cx = ((x - g.info.origin.translation.x) / 0.1).floor() as usize;
            let cy = ((y - g.info.origin.translation.y) / 0.1).floor() as usize;
            g.data[cy * w + cx] as i8
        };
        assert_eq!(at(2.05, 0.0), 100);
        assert_eq!(at(1.0, 0.0), 0);
        // The grid over z above everything seen: all unknown.
        let high = grid(&view, "map", 5.0, 6.0).unwrap();
        assert!(high.data.iter().all(|&c| c as i8 == -1));
        // A range that holds no voxel centre: an empty grid.
        let none = grid(&view, "map", 0.11, 0.12).unwrap();
        assert_eq!((none.info.width, none.data.len()), (0, 0));
    }
}

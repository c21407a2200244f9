//! `sensor_msgs/msg/PointCloud2` to points: x, y and z found by name, FLOAT32 or FLOAT64,
//! at any offsets and in any order, in either byte order, organized or not; every other
//! field is ignored. Points with a non-finite coordinate are skipped and counted.

use crate::msg::PointCloud2;

/// `sensor_msgs/msg/PointField` datatype codes.
pub mod datatype {
    pub const INT8: u8 = 1;
    pub const UINT8: u8 = 2;
    pub const INT16: u8 = 3;
    pub const UINT16: u8 = 4;
    pub const INT32: u8 = 5;
    pub const UINT32: u8 = 6;
    pub const FLOAT32: u8 = 7;
    pub const FLOAT64: u8 = 8;

    /// Bytes of one element of `datatype`, or `None` for a code ROS does not define.
    pub fn size(datatype: u8) -> Option<u32> {
        match datatype {
            INT8 | UINT8 => Some(1),
            INT16 | UINT16 => Some(2),
            INT32 | UINT32 | FLOAT32 => Some(4),
            FLOAT64 => Some(8),
            _ => None,
        }
    }
}

/// Most points one cloud may declare: 2^28 (a 4 GB float32 xyz cloud), far beyond any
/// sensor, so that a lying width or height cannot ask for an absurd allocation.
pub const MAX_POINTS: u64 = 1 << 28;

/// The finite points of a cloud, in its own frame.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct CloudPoints {
    pub points: Vec<[f32; 3]>,
    /// Points skipped for a NaN or infinite coordinate (or a float64 beyond float32).
    pub non_finite: u64,
}

/// Why a cloud cannot be read. Each names what is wrong in the message's own terms.
#[derive(Debug, Clone, PartialEq)]
pub enum CloudError {
    /// No field named `x`, `y` or `z`.
    MissingField(&'static str),
    /// x, y or z is not FLOAT32 or FLOAT64.
    FieldType { name: &'static str, datatype: u8 },
    /// A coordinate field does not fit in `point_step`.
    FieldOutsidePoint {
        name: &'static str,
        offset: u32,
        point_step: u32,
    },
    /// `row_step` is shorter than `width * point_step`.
    RowStep {
        row_step: u32,
        width: u32,
        point_step: u32,
    },
    /// `data` is not `height * row_step` bytes.
    DataSize { expected: u64, actual: usize },
    /// More than [`MAX_POINTS`] points.
    TooManyPoints(u64),
}

impl CloudError {
    /// A short name of the kind of problem, for counting skipped clouds by reason.
    pub fn kind(&self) -> &'static str {
        match self {
            Self::MissingField(_) => "no x, y or z field",
            Self::FieldType { .. } => "coordinate not float32/float64",
            Self::FieldOutsidePoint { .. } => "field outside the point",
            Self::RowStep { .. } => "row_step shorter than a row",
            Self::DataSize { .. } => "data size disagrees",
            Self::TooManyPoints(_) => "too many points",
        }
    }
}

impl std::fmt::Display for CloudError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::MissingField(n) => write!(f, "the cloud has no '{n}' field"),
            Self::FieldType { name, datatype } => write!(
                f,
                "field '{name}' has datatype {datatype}; coordinates must be FLOAT32 (7) or FLOAT64 (8)"
            ),
            Self::FieldOutsidePoint {
                name,
                offset,
                point_step,
            } => write!(
                f,
                "field '{name}' at offset {offset} does not fit in point_step {point_step}"
            ),
            Self::RowStep {
                row_step,
                width,
                point_step,
            } => write!(
                f,
                "row_step {row_step} is less than width {width} x point_step {point_step}"
            ),
            Self::DataSize { expected, actual } => write!(
                f,
                "data holds {actual} bytes but height x row_step is {expected}"
            ),
            Self::TooManyPoints(n) => write!(f, "{n} points is more than {MAX_POINTS}"),
        }
    }
}

impl std::error::Error for CloudError {}

/// Where a coordinate is within a point, and how it is stored.
#[derive(Clone, Copy)]
struct Coord {
    offset: usize,
    f64: bool,
}

/// Read the points of `cloud`. The cloud is validated before any point is read.
pub fn points(cloud: &PointCloud2<impl AsRef<[u8]>>) -> Result<CloudPoints, CloudError> {
    let data = cloud.data.as_ref();
    let mut coords = [Coord {
        offset: 0,
        f64: false,
    }; 3];
    for (k, name) in ["x", "y", "z"].into_iter().enumerate() {
        let f = cloud
            .fields
            .iter()
            .find(|f| f.name == name)
            .ok_or(CloudError::MissingField(name))?;
        let size = match f.datatype {
            datatype::FLOAT32 => 4,
            datatype::FLOAT64 => 8,
            d => return Err(CloudError::FieldType { name, datatype: d }),
        };
        if u64::from(f.offset) + size > u64::from(cloud.point_step) {
            return Err(CloudError::FieldOutsidePoint {
                name,
                offset: f.offset,
                point_step: cloud.point_step,
            });
        }
        coords[k] = Coord {
            offset: f.offset as usize,
            f64: size == 8,
        };
    }
    let (h, w) = (u64::from(cloud.height), u64::from(cloud.width));
    if h * w > MAX_POINTS {
        return Err(CloudError::TooManyPoints(h * w));
    }
    if u64::from(cloud.row_step) < w * u64::from(cloud.point_step) {
        return Err(CloudError::RowStep {
            row_step: cloud.row_step,
            width: cloud.width,
            point_step: cloud.point_step,
        });
    }
    let expected = h * u64::from(cloud.row_step);
    if expected != data.len() as u64 {
        return Err(CloudError::DataSize {
            expected,
            actual: data.len(),
        });
    }
    let mut out = CloudPoints {
        points: Vec::with_capacity((h * w) as usize),
        non_finite: 0,
    };
    let [x, y, z] = coords.map(|c| c.offset);
    // One monomorphic loop per common layout; mixed float sizes take the general one.
    match (coords.map(|c| c.f64), cloud.is_bigendian) {
        ([false, false, false], false) => read_rows(cloud, &mut out, |p| {
            [f32_le(p, x), f32_le(p, y), f32_le(p, z)]
        }),
        ([false, false, false], true) => read_rows(cloud, &mut out, |p| {
            [f32_be(p, x), f32_be(p, y), f32_be(p, z)]
        }),
        ([true, true, true], false) => read_rows(cloud, &mut out, |p| {
            [f64_le(p, x), f64_le(p, y), f64_le(p, z)].map(|v| v as f32)
        }),
        ([true, true, true], true) => read_rows(cloud, &mut out, |p| {
            [f64_be(p, x), f64_be(p, y), f64_be(p, z)].map(|v| v as f32)
        }),
        (wide, big) => read_rows(cloud, &mut out, |p| {
            let read = |k: usize, o: usize| match (wide[k], big) {
                (false, false) => f32_le(p, o),
                (false, true) => f32_be(p, o),
                (true, false) => f64_le(p, o) as f32,
                (true, true) => f64_be(p, o) as f32,
            };
            [read(0, x), read(1, y), read(2, z)]
        }),
    }
    Ok(out)
}

/// Every point of every row through `read` (given the point's `point_step` bytes),
/// keeping the finite ones. The caller checked that all rows and points are in `data`.
#[inline(always)]
fn read_rows(
    cloud: &PointCloud2<impl AsRef<[u8]>>,
    out: &mut CloudPoints,
    read: impl Fn(&[u8]) -> [f32; 3],
) {
    let (row_step, step) = (cloud.row_step as usize, cloud.point_step as usize);
    let row_len = cloud.width as usize * step;
    if row_step == 0 || step == 0 {
        // Zero-sized points or rows (width or height 0, or point_step 0 with width 0).
        return;
    }
    for row in cloud.data.as_ref().chunks_exact(row_step) {
        for p in row[..row_len].chunks_exact(step) {
            let v = read(p);
            if v[0].is_finite() && v[1].is_finite() && v[2].is_finite() {
                out.points.push(v);
            } else {
                out.non_finite += 1;
            }
        }
    }
}

#[inline(always)]
fn f32_le(p: &[u8], o: usize) -> f32 {
    f32::from_le_bytes(p[o..o + 4].try_into().unwrap_or_default())
}
#[inline(always)]
fn f32_be(p: &[u8], o: usize) -> f32 {
    f32::from_be_bytes(p[o..o + 4].try_into().unwrap_or_default())
}
#[inline(always)]
fn f64_le(p: &[u8], o: usize) -> f64 {
    f64::from_le_bytes(p[o..o + 8].try_into().unwrap_or_default())
}
#[inline(always)]
fn f64_be(p: &[u8], o: usize) -> f64 {
    f64::from_be_bytes(p[o..o + 8].try_into().unwrap_or_default())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::msg::{Header, PointField, Time};

    fn field(name: &str, offset: u32, datatype: u8) -> PointField {
        PointField {
            name: name.into(),
            offset,
            datatype,
            count: 1,
        }
    }

    fn cloud(
        fields: Vec<PointField>,
        step: u32,
        w: u32,
        h: u32,
        data: &[u8],
    ) -> PointCloud2<&[u8]> {
        PointCloud2 {
            header: Header {
                stamp: Time { sec: 0, nanosec: 0 },
                frame_id: "s".into(),
            },
            height: h,
            width: w,
            fields,
            is_bigendian: false,
            point_step: step,
            row_step: step.wrapping_mul(w),
            data,
            is_dense: true,
        }
    }

    #[test]
    fn fields_in_any_order_and_size_with_padding_and_row_padding() {
        // z float64 at 0, intensity at 8, x float32 at 12, y float64 at 16; 28-byte points,
        // two rows of two points with 4 bytes of row padding.
        let pts = [
            [1.0f32, 2.0, 3.0],
            [4.0, 5.0, 6.0],
            [f32::NAN, 0.0, 0.0],
            [7.0, 8.0, 9.0],
        ];
        let mut data = Vec::new();
        for row in pts.chunks(2) {
            for p in row {
                data.extend((p[2] as f64).to_le_bytes());
                data.extend(9.5f32.to_le_bytes());
                data.extend(p[0].to_le_bytes());
                data.extend((p[1] as f64).to_le_bytes());
            }
            data.extend([0xAA; 4]);
        }
        let fields = vec![
            field("z", 0, datatype::FLOAT64),
            field("intensity", 8, datatype::FLOAT32),
            field("x", 12, datatype::FLOAT32),
            field("y", 16, datatype::FLOAT64),
        ];
        let mut c = cloud(fields, 24, 2, 2, &data);
        c.row_step = 52;
        let r = points(&c).unwrap();
        assert_eq!(r.points, vec![pts[0], pts[1], pts[3]]);
        assert_eq!(r.non_finite, 1);
    }

    #[test]
    fn big_endian_clouds_are_read_in_their_byte_order() {
        let mut data = Vec::new();
        for v in [1.5f32, -2.0, 3.25, f32::INFINITY, 0.0, 0.0] {
            data.extend(v.to_be_bytes());
        }
        let f = vec![
            field("x", 0, datatype::FLOAT32),
            field("y", 4, datatype::FLOAT32),
            field("z", 8, datatype::FLOAT32),
        ];
        let mut c = cloud(f, 12, 2, 1, &data);
        c.is_bigendian = true;
        let r = points(&c).unwrap();
        assert_eq!(r.points, vec![[1.5, -2.0, 3.25]]);
        assert_eq!(r.non_finite, 1);
    }

    #[test]
    fn each_inconsistency_is_named() {
        let data = [0u8; 24];
        let xyz = || {
            vec![
                field("x", 0, datatype::FLOAT32),
                field("y", 4, datatype::FLOAT32),
                field("z", 8, datatype::FLOAT32),
            ]
        };
        let mut f = xyz();
        f.pop();
        assert_eq!(
            points(&cloud(f, 12, 2, 1, &data)),
            Err(CloudError::MissingField("z"))
        );
        let mut f = xyz();
        f[1].datatype = datatype::INT16;
        assert!(matches!(
            points(&cloud(f, 12, 2, 1, &data)),
            Err(CloudError::FieldType { name: "y", .. })
        ));
        let mut f = xyz();
        f[2].offset = 10;
        assert!(matches!(
            points(&cloud(f, 12, 2, 1, &data)),
            Err(CloudError::FieldOutsidePoint { name: "z", .. })
        ));
        let mut c = cloud(xyz(), 12, 2, 1, &data);
        c.row_step = 20;
        assert!(matches!(points(&c), Err(CloudError::RowStep { .. })));
        assert_eq!(
            points(&cloud(xyz(), 12, 3, 1, &data)),
            Err(CloudError::DataSize {
                expected: 36,
                actual: 24
            })
        );
        assert!(matches!(
            points(&cloud(xyz(), 12, u32::MAX, u32::MAX, &data)),
            Err(CloudError::TooManyPoints(_))
        ));
        // An empty cloud is valid and has no points.
        assert_eq!(
            points(&cloud(xyz(), 12, 0, 0, &[])).unwrap().points.len(),
            0
        );
    }
}

/// Serialized clouds, as a ROS 2 publisher would write them (CDR, little endian), and
/// damaged ones: decoding and reading never panic, whatever the bytes.
#[cfg(test)]
mod cdr_tests {
    use super::*;
    use crate::msg;
    use proptest::prelude::*;

    /// A CDR writer just big enough for a PointCloud2 (alignment from the body's start).
    struct Cdr(Vec<u8>);
    impl Cdr {
        fn align(&mut self, n: usize) {
            while !(self.0.len() - 4).is_multiple_of(n) {
                self.0.push(0);
            }
        }
        fn u32(&mut self, v: u32) {
            self.align(4);
            self.0.extend(v.to_le_bytes());
        }
        fn u8(&mut self, v: u8) {
            self.0.push(v);
        }
        fn string(&mut self, s: &str) {
            self.u32(s.len() as u32 + 1);
            self.0.extend(s.as_bytes());
            self.0.push(0);
        }
    }

    fn serialized(points: &[[f32; 3]]) -> Vec<u8> {
        let mut c = Cdr(vec![0, 1, 0, 0]);
        c.u32(7); // stamp.sec
        c.u32(9); // stamp.nanosec
        c.string("lidar");
        c.u32(1); // height
        c.u32(points.len() as u32);
        c.u32(4); // fields
        for (name, off, dt) in [
            ("x", 0, 7u8),
            ("y", 4, 7),
            ("z", 8, 7),
            ("intensity", 12, 7),
        ] {
            c.string(name);
            c.u32(off);
            c.u8(dt);
            c.u32(1);
        }
        c.u8(0); // is_bigendian
        c.u32(16);
        c.u32(16 * points.len() as u32);
        c.u32(16 * points.len() as u32);
        for p in points {
            for v in [p[0], p[1], p[2], 0.5] {
                c.0.extend(v.to_le_bytes());
            }
        }
        c.u8(1); // is_dense
        c.0
    }

    #[test]
    fn a_serialized_cloud_decodes_to_its_points() {
        let pts = [[1.0, 2.0, 3.0], [-4.0, 5.5, 0.25]];
        let bytes = serialized(&pts);
        let c: msg::PointCloud2<&[u8]> = msg::decode(&bytes).unwrap();
        assert_eq!(
            (c.header.stamp.ns(), c.header.frame_id.as_str()),
            (7_000_000_009, "lidar")
        );
        assert_eq!(points(&c).unwrap().points, pts.to_vec());
    }

    proptest! {
        #[test]
        fn damaged_clouds_never_panic(
            n in 0usize..40,
            flips in proptest::collection::vec((any::<usize>(), any::<u8>()), 0..8),
            cut in any::<usize>(),
        ) {
            let pts: Vec<[f32; 3]> = (0..n).map(|i| [i as f32, 1.0, 2.0]).collect();
            let mut bytes = serialized(&pts);
            for (at, v) in flips {
                let k = at % bytes.len();
                bytes[k] = v;
            }
            bytes.truncate(cut % (bytes.len() + 1));
            if let Ok(c) = msg::decode::<msg::PointCloud2<&[u8]>>(&bytes) {
                if let Ok(r) = points(&c) {
                    prop_assert!(r.points.len() as u64 + r.non_finite <= u64::from(c.width) * u64::from(c.height));
                }
            }
        }
    }
}

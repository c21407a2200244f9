//! PCD v0.7 point clouds (ascii and binary) with float `x y z` fields among others; the
//! sensor pose comes from `VIEWPOINT` (tx ty tz qw qx qy qz).

use super::{Format, ParseError, ReadError, ReadErrorKind};
use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion};
use std::path::Path;

/// A point cloud in the sensor frame with the sensor's pose.
#[derive(Clone, Debug, PartialEq)]
pub struct PointCloud {
    pub points: Vec<[f32; 3]>,
    pub pose: Isometry3<f64>,
}

/// Read a PCD file.
pub fn read(path: &Path) -> Result<PointCloud, ReadError> {
    let fail = |kind| ReadError {
        path: path.into(),
        kind,
    };
    let bytes = std::fs::read(path).map_err(|e| fail(ReadErrorKind::Io(e)))?;
    parse(&bytes).map_err(|e| fail(ReadErrorKind::Parse(e)))
}

/// Parse PCD bytes: the header, then the points it describes.
pub fn parse(bytes: &[u8]) -> Result<PointCloud, ParseError> {
    let (header, data_at) = Header::parse(bytes)?;
    let layout = header.layout()?;
    let pose = header.pose()?;
    let data = &bytes[data_at..];
    let points = match header.data.as_str() {
        "binary" => read_binary(data, header.points, &layout)?,
        "ascii" => read_ascii(data, header.points, &header.counts, &layout)?,
        "binary_compressed" => return Err(bad(
            "DATA binary_compressed is not supported (convert with pcl_convert_pcd_ascii_binary)",
        )),
        other => return Err(bad(format!("unknown DATA kind '{other}'"))),
    };
    Ok(PointCloud { points, pose })
}

/// A PCD problem.
fn bad(problem: impl Into<String>) -> ParseError {
    ParseError {
        format: Format::Pcd,
        problem: problem.into(),
    }
}

/// A PCD header, its fields checked against each other.
struct Header {
    fields: Vec<String>,
    sizes: Vec<usize>,
    types: Vec<String>,
    counts: Vec<usize>,
    /// Points in the data.
    points: usize,
    /// tx ty tz qw qx qy qz.
    viewpoint: [f64; 7],
    /// `binary`, `ascii`, ... (lower case).
    data: String,
}

#[derive(Clone, Copy)]
struct Field {
    offset: usize,
    size: usize,
    float: bool,
}

/// Where a point's fields lie in a binary record, and the x, y and z fields.
struct Layout {
    /// Bytes per point.
    record: usize,
    /// x, y and z: each field's index and place.
    xyz: [(usize, Field); 3],
}

impl Header {
    /// The header at the start of `bytes`, and where its data starts.
    fn parse(bytes: &[u8]) -> Result<(Header, usize), ParseError> {
        let mut pos = 0;
        let mut h = Header {
            fields: Vec::new(),
            sizes: Vec::new(),
            types: Vec::new(),
            counts: Vec::new(),
            points: 0,
            viewpoint: [0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0],
            data: String::new(),
        };
        let (mut width, mut height, mut points): (Option<usize>, Option<usize>, Option<usize>) =
            (None, None, None);
        loop {
            if pos >= bytes.len() {
                return Err(bad("header ends without a DATA line"));
            }
            let end = bytes[pos..]
                .iter()
                .position(|&b| b == b'\n')
                .map_or(bytes.len(), |i| pos + i);
            let line =
                std::str::from_utf8(&bytes[pos..end]).map_err(|_| bad("header is not text"))?;
            pos = (end + 1).min(bytes.len());
            let line = line.trim();
            if line.is_empty() || line.starts_with('#') {
                continue;
            }
            let mut it = line.split_whitespace();
            let key = it.next().unwrap_or("").to_ascii_uppercase();
            let rest: Vec<&str> = it.collect();
            let num = |s: &str| {
                s.parse::<usize>()
                    .map_err(|_| bad(format!("{key}: '{s}' is not a count")))
            };
            match key.as_str() {
                "VERSION" => {
                    if !rest
                        .first()
                        .is_some_and(|v| v.trim_start_matches('.') == "7" || *v == "0.7")
                    {
                        return Err(bad(format!("unsupported PCD VERSION {}", rest.join(" "))));
                    }
                }
                "FIELDS" => h.fields = rest.iter().map(|s| s.to_string()).collect(),
                "SIZE" => h.sizes = rest.iter().map(|s| num(s)).collect::<Result<_, _>>()?,
                "TYPE" => h.types = rest.iter().map(|s| s.to_string()).collect(),
                "COUNT" => h.counts = rest.iter().map(|s| num(s)).collect::<Result<_, _>>()?,
                "WIDTH" => width = Some(num(rest.first().unwrap_or(&""))?),
                "HEIGHT" => height = Some(num(rest.first().unwrap_or(&""))?),
                "POINTS" => points = Some(num(rest.first().unwrap_or(&""))?),
                "VIEWPOINT" => {
                    if rest.len() != 7 {
                        return Err(bad(format!(
                            "VIEWPOINT needs 7 numbers, got {}",
                            rest.len()
                        )));
                    }
                    for (v, s) in h.viewpoint.iter_mut().zip(&rest) {
                        *v = s
                            .parse::<f64>()
                            .map_err(|_| bad(format!("VIEWPOINT: '{s}' is not a number")))?;
                    }
                }
                "DATA" => {
                    h.data = rest
                        .first()
                        .map(|s| s.to_ascii_lowercase())
                        .unwrap_or_default();
                    break;
                }
                _ => return Err(bad(format!("unknown header line '{line}'"))),
            }
        }
        if h.counts.is_empty() {
            h.counts = vec![1; h.fields.len()];
        }
        let n = h.fields.len();
        if n == 0 || h.sizes.len() != n || h.types.len() != n || h.counts.len() != n {
            return Err(bad(format!(
                "FIELDS/SIZE/TYPE/COUNT disagree: {n} fields, {} sizes, {} types, {} counts",
                h.sizes.len(),
                h.types.len(),
                h.counts.len()
            )));
        }
        h.points = match (points, width, height) {
            (Some(p), Some(w), Some(h)) if w.checked_mul(h) != Some(p) => {
                return Err(bad(format!(
                    "POINTS {p} disagrees with WIDTH*HEIGHT {w}*{h}"
                )))
            }
            (Some(p), _, _) => p,
            (None, Some(w), Some(h)) => w
                .checked_mul(h)
                .ok_or_else(|| bad("WIDTH*HEIGHT overflows"))?,
            _ => return Err(bad("no POINTS or WIDTH/HEIGHT in header")),
        };
        Ok((h, pos))
    }

    /// Each field's place in a binary record, and the x, y and z fields (float32 or
    /// float64, one value each).
    fn layout(&self) -> Result<Layout, ParseError> {
        let mut fields = Vec::with_capacity(self.fields.len());
        let mut offset = 0usize;
        for (i, name) in self.fields.iter().enumerate() {
            let (size, ty) = (self.sizes[i], self.types[i].as_str());
            if !matches!(size, 1 | 2 | 4 | 8) || !matches!(ty, "F" | "I" | "U") {
                return Err(bad(format!(
                    "field {name}: unsupported SIZE {size} TYPE {ty}"
                )));
            }
            fields.push(Field {
                offset,
                size,
                float: ty == "F",
            });
            offset = size
                .checked_mul(self.counts[i])
                .and_then(|b| offset.checked_add(b))
                .ok_or_else(|| bad("record size overflows"))?;
        }
        let find = |name: &str| -> Result<(usize, Field), ParseError> {
            let i = self
                .fields
                .iter()
                .position(|f| f == name)
                .ok_or_else(|| bad(format!("no '{name}' field")))?;
            let f = fields[i];
            if !f.float || !(f.size == 4 || f.size == 8) || self.counts[i] != 1 {
                return Err(bad(format!(
                    "field '{name}' must be a float32/float64 with COUNT 1"
                )));
            }
            Ok((i, f))
        };
        Ok(Layout {
            record: offset,
            xyz: [find("x")?, find("y")?, find("z")?],
        })
    }

    /// The sensor pose `VIEWPOINT` gives.
    fn pose(&self) -> Result<Isometry3<f64>, ParseError> {
        let [tx, ty, tz, qw, qx, qy, qz] = self.viewpoint;
        let q = Quaternion::new(qw, qx, qy, qz);
        if !self.viewpoint.iter().all(|v| v.is_finite()) || (q.norm() - 1.0).abs() > 1e-3 {
            return Err(bad(format!(
                "VIEWPOINT {:?} is not a finite pose with a unit quaternion",
                self.viewpoint
            )));
        }
        Ok(Isometry3::from_parts(
            Translation3::new(tx, ty, tz),
            UnitQuaternion::from_quaternion(q),
        ))
    }
}

/// `n` binary records of `layout` at the start of `data`.
fn read_binary(data: &[u8], n: usize, layout: &Layout) -> Result<Vec<[f32; 3]>, ParseError> {
    let record = layout.record;
    let need = n
        .checked_mul(record)
        .ok_or_else(|| bad("POINTS * record size overflows"))?;
    if data.len() < need {
        return Err(bad(format!(
            "truncated binary data: {n} points of {record} bytes need {need} bytes, file has {}",
            data.len()
        )));
    }
    let read = |rec: &[u8], f: Field| -> f32 {
        if f.size == 4 {
            f32::from_le_bytes(rec[f.offset..f.offset + 4].try_into().expect("4 bytes"))
        } else {
            f64::from_le_bytes(rec[f.offset..f.offset + 8].try_into().expect("8 bytes")) as f32
        }
    };
    let [x, y, z] = layout.xyz.map(|(_, f)| f);
    Ok(data[..need]
        .chunks_exact(record)
        .map(|rec| [read(rec, x), read(rec, y), read(rec, z)])
        .collect())
}

/// `n` ascii lines of values, `counts` a field, at the start of `data`.
fn read_ascii(
    data: &[u8],
    n: usize,
    counts: &[usize],
    layout: &Layout,
) -> Result<Vec<[f32; 3]>, ParseError> {
    let text = std::str::from_utf8(data).map_err(|_| bad("ascii data is not text"))?;
    // Column of each field's first value.
    let mut col = Vec::with_capacity(counts.len());
    let mut c = 0;
    for &k in counts {
        col.push(c);
        c += k;
    }
    let mut out = Vec::with_capacity(n.min(1 << 24));
    for (ln, line) in text.lines().filter(|l| !l.trim().is_empty()).enumerate() {
        if ln >= n {
            break;
        }
        let vals: Vec<&str> = line.split_whitespace().collect();
        if vals.len() != c {
            return Err(bad(format!(
                "ascii point {ln}: {} values, header says {c}",
                vals.len()
            )));
        }
        let g = |i: usize| -> Result<f32, ParseError> {
            let s = vals[col[layout.xyz[i].0]];
            match s.to_ascii_lowercase().as_str() {
                "nan" => Ok(f32::NAN),
                _ => s
                    .parse::<f32>()
                    .map_err(|_| bad(format!("ascii point {ln}: '{s}' is not a number"))),
            }
        };
        out.push([g(0)?, g(1)?, g(2)?]);
    }
    if out.len() != n {
        return Err(bad(format!(
            "truncated ascii data: header says {n} points, file has {}",
            out.len()
        )));
    }
    Ok(out)
}

/// Write a binary PCD (x y z float32) with the pose in VIEWPOINT.
pub fn write(path: &Path, cloud: &PointCloud) -> std::io::Result<()> {
    std::fs::write(path, encode(cloud))
}

/// Binary PCD bytes (x y z float32) with the pose in VIEWPOINT.
pub fn encode(cloud: &PointCloud) -> Vec<u8> {
    let t = cloud.pose.translation.vector;
    let q = cloud.pose.rotation.quaternion();
    let n = cloud.points.len();
    let mut out = format!(
        "# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\n\
         WIDTH {n}\nHEIGHT 1\nVIEWPOINT {} {} {} {} {} {} {}\nPOINTS {n}\nDATA binary\n",
        t.x, t.y, t.z, q.w, q.i, q.j, q.k
    )
    .into_bytes();
    for p in &cloud.points {
        for c in p {
            out.extend_from_slice(&c.to_le_bytes());
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    const HDR: &str = "VERSION 0.7\nFIELDS x y z intensity\nSIZE 4 4 4 4\nTYPE F F F F\nCOUNT 1 1 1 1\nWIDTH 2\nHEIGHT 1\nVIEWPOINT 1 2 3 1 0 0 0\nPOINTS 2\n";

    #[test]
    fn binary_round_trip_with_pose() {
        let pose = Isometry3::from_parts(
            Translation3::new(1.0, -2.0, 0.5),
            UnitQuaternion::from_euler_angles(0.1, 0.2, 0.3),
        );
        let cloud = PointCloud {
            points: vec![[1.0, 2.0, 3.0], [-4.0, 5.5, f32::NAN]],
            pose,
        };
        let back = parse(&encode(&cloud)).unwrap();
        assert_eq!(back.points[0], [1.0, 2.0, 3.0]);
        assert!(back.points[1][2].is_nan());
        assert!((back.pose.translation.vector - pose.translation.vector).norm() < 1e-9);
        assert!(back.pose.rotation.angle_to(&pose.rotation) < 1e-6);
    }

    #[test]
    fn ascii_with_extra_fields() {
        let text = format!("{HDR}DATA ascii\n1 2 3 9\n4 5 nan 9\n");
        let c = parse(text.as_bytes()).unwrap();
        assert_eq!(c.points[0], [1.0, 2.0, 3.0]);
        assert!(c.points[1][2].is_nan());
        assert_eq!(c.pose.translation.vector.x, 1.0);
    }

    #[test]
    fn binary_with_extra_fields_picks_xyz() {
        let mut b = format!("{HDR}DATA binary\n").into_bytes();
        for v in [1.0f32, 2.0, 3.0, 99.0, 4.0, 5.0, 6.0, 99.0] {
            b.extend_from_slice(&v.to_le_bytes());
        }
        assert_eq!(
            parse(&b).unwrap().points,
            vec![[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]]
        );
    }

    #[test]
    fn bad_files_say_what_is_wrong() {
        let cases = [
            (format!("{HDR}DATA binary\n\0\0\0\0"), "truncated binary"),
            (
                format!("{HDR}DATA binary_compressed\n"),
                "binary_compressed",
            ),
            (format!("{HDR}DATA ascii\n1 2 3 9\n"), "truncated ascii"),
            (
                HDR.replace("FIELDS x y z", "FIELDS a b c") + "DATA ascii\n",
                "no 'x' field",
            ),
            (
                HDR.replace("SIZE 4 4 4 4", "SIZE 4 4 4") + "DATA ascii\n",
                "disagree",
            ),
            (
                HDR.replace("POINTS 2", "POINTS 3") + "DATA ascii\n",
                "disagrees with WIDTH",
            ),
            (
                HDR.replace("VIEWPOINT 1 2 3 1 0 0 0", "VIEWPOINT 1 2 3 2 0 0 0") + "DATA ascii\n",
                "unit quaternion",
            ),
            ("VERSION 0.7\nFIELDS x y z\n".to_string(), "DATA"),
            (
                HDR.replace("TYPE F F F F", "TYPE I F F F") + "DATA ascii\n",
                "float32",
            ),
        ];
        for (text, want) in cases {
            let err = parse(text.as_bytes()).unwrap_err();
            assert!(
                err.problem.contains(want),
                "{err:?} should mention {want:?}"
            );
        }
        let e = read(Path::new("/nonexistent/x.pcd")).unwrap_err();
        assert!(e.to_string().contains("/nonexistent/x.pcd"));
    }
}

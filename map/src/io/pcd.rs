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

/// Parse PCD bytes.
pub fn parse(bytes: &[u8]) -> Result<PointCloud, ParseError> {
    parse_pcd(bytes).map_err(ParseError::new(Format::Pcd))
}

#[derive(Clone, Copy)]
struct Field {
    offset: usize,
    size: usize,
    float: bool,
}

fn parse_pcd(bytes: &[u8]) -> Result<PointCloud, String> {
    let mut pos = 0;
    let mut fields: Vec<String> = Vec::new();
    let (mut sizes, mut types, mut counts) = (Vec::new(), Vec::new(), Vec::new());
    let (mut width, mut height, mut points): (Option<usize>, Option<usize>, Option<usize>) =
        (None, None, None);
    let mut viewpoint = [0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0];
    let data_kind = loop {
        if pos >= bytes.len() {
            return Err("header ends without a DATA line".into());
        }
        let end = bytes[pos..]
            .iter()
            .position(|&b| b == b'\n')
            .map_or(bytes.len(), |i| pos + i);
        let line =
            std::str::from_utf8(&bytes[pos..end]).map_err(|_| "header is not text".to_string())?;
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
                .map_err(|_| format!("{key}: '{s}' is not a count"))
        };
        match key.as_str() {
            "VERSION" => {
                if !rest
                    .first()
                    .is_some_and(|v| v.trim_start_matches('.') == "7" || *v == "0.7")
                {
                    return Err(format!("unsupported PCD VERSION {}", rest.join(" ")));
                }
            }
            "FIELDS" => fields = rest.iter().map(|s| s.to_string()).collect(),
            "SIZE" => sizes = rest.iter().map(|s| num(s)).collect::<Result<_, _>>()?,
            "TYPE" => types = rest.iter().map(|s| s.to_string()).collect(),
            "COUNT" => counts = rest.iter().map(|s| num(s)).collect::<Result<_, _>>()?,
            "WIDTH" => width = Some(num(rest.first().unwrap_or(&""))?),
            "HEIGHT" => height = Some(num(rest.first().unwrap_or(&""))?),
            "POINTS" => points = Some(num(rest.first().unwrap_or(&""))?),
            "VIEWPOINT" => {
                if rest.len() != 7 {
                    return Err(format!("VIEWPOINT needs 7 numbers, got {}", rest.len()));
                }
                for (v, s) in viewpoint.iter_mut().zip(&rest) {
                    *v = s
                        .parse::<f64>()
                        .map_err(|_| format!("VIEWPOINT: '{s}' is not a number"))?;
                }
            }
            "DATA" => {
                break rest
                    .first()
                    .map(|s| s.to_ascii_lowercase())
                    .unwrap_or_default()
            }
            _ => return Err(format!("unknown header line '{line}'")),
        }
    };
    if counts.is_empty() {
        counts = vec![1; fields.len()];
    }
    if fields.is_empty()
        || sizes.len() != fields.len()
        || types.len() != fields.len()
        || counts.len() != fields.len()
    {
        return Err(format!(
            "FIELDS/SIZE/TYPE/COUNT disagree: {} fields, {} sizes, {} types, {} counts",
            fields.len(),
            sizes.len(),
            types.len(),
            counts.len()
        ));
    }
    let n = match (points, width, height) {
        (Some(p), Some(w), Some(h)) if w.checked_mul(h) != Some(p) => {
            return Err(format!("POINTS {p} disagrees with WIDTH*HEIGHT {w}*{h}"))
        }
        (Some(p), _, _) => p,
        (None, Some(w), Some(h)) => w.checked_mul(h).ok_or("WIDTH*HEIGHT overflows")?,
        _ => return Err("no POINTS or WIDTH/HEIGHT in header".into()),
    };
    let mut layout = Vec::new();
    let mut offset = 0usize;
    for i in 0..fields.len() {
        if !matches!(sizes[i], 1 | 2 | 4 | 8) || !matches!(types[i].as_str(), "F" | "I" | "U") {
            return Err(format!(
                "field {}: unsupported SIZE {} TYPE {}",
                fields[i], sizes[i], types[i]
            ));
        }
        layout.push(Field {
            offset,
            size: sizes[i],
            float: types[i] == "F",
        });
        offset = sizes[i]
            .checked_mul(counts[i])
            .and_then(|b| offset.checked_add(b))
            .ok_or("record size overflows")?;
    }
    let record = offset;
    let xyz: Vec<(usize, Field)> = ["x", "y", "z"]
        .iter()
        .map(|name| {
            let i = fields
                .iter()
                .position(|f| f == name)
                .ok_or(format!("no '{name}' field"))?;
            let f = layout[i];
            if !f.float || !(f.size == 4 || f.size == 8) || counts[i] != 1 {
                return Err(format!(
                    "field '{name}' must be a float32/float64 with COUNT 1"
                ));
            }
            Ok((i, f))
        })
        .collect::<Result<_, String>>()?;
    let [tx, ty, tz, qw, qx, qy, qz] = viewpoint;
    let q = Quaternion::new(qw, qx, qy, qz);
    if !viewpoint.iter().all(|v| v.is_finite()) || (q.norm() - 1.0).abs() > 1e-3 {
        return Err(format!(
            "VIEWPOINT {viewpoint:?} is not a finite pose with a unit quaternion"
        ));
    }
    let pose = Isometry3::from_parts(
        Translation3::new(tx, ty, tz),
        UnitQuaternion::from_quaternion(q),
    );
    let data = &bytes[pos..];
    let points = match data_kind.as_str() {
        "binary" => {
            let need = n
                .checked_mul(record)
                .ok_or("POINTS * record size overflows")?;
            if data.len() < need {
                return Err(format!(
                    "truncated binary data: {} points of {record} bytes need {need} bytes, file has {}",
                    n,
                    data.len()
                ));
            }
            let read = |rec: &[u8], f: Field| -> f32 {
                if f.size == 4 {
                    f32::from_le_bytes(rec[f.offset..f.offset + 4].try_into().expect("4 bytes"))
                } else {
                    f64::from_le_bytes(rec[f.offset..f.offset + 8].try_into().expect("8 bytes"))
                        as f32
                }
            };
            data[..need]
                .chunks_exact(record)
                .map(|rec| {
                    [
                        read(rec, xyz[0].1),
                        read(rec, xyz[1].1),
                        read(rec, xyz[2].1),
                    ]
                })
                .collect()
        }
        "ascii" => {
            let text =
                std::str::from_utf8(data).map_err(|_| "ascii data is not text".to_string())?;
            // Column of each field's first value.
            let mut col = Vec::with_capacity(fields.len());
            let mut c = 0;
            for &k in &counts {
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
                    return Err(format!(
                        "ascii point {ln}: {} values, header says {c}",
                        vals.len()
                    ));
                }
                let g = |i: usize| -> Result<f32, String> {
                    let s = vals[col[xyz[i].0]];
                    match s.to_ascii_lowercase().as_str() {
                        "nan" => Ok(f32::NAN),
                        _ => s
                            .parse::<f32>()
                            .map_err(|_| format!("ascii point {ln}: '{s}' is not a number")),
                    }
                };
                out.push([g(0)?, g(1)?, g(2)?]);
            }
            if out.len() != n {
                return Err(format!(
                    "truncated ascii data: header says {n} points, file has {}",
                    out.len()
                ));
            }
            out
        }
        "binary_compressed" => return Err(
            "DATA binary_compressed is not supported (convert with pcl_convert_pcd_ascii_binary)"
                .into(),
        ),
        other => return Err(format!("unknown DATA kind '{other}'")),
    };
    Ok(PointCloud { points, pose })
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

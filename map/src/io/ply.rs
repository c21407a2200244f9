//! PLY point clouds: read the `vertex` element's float `x y z` (ascii or binary
//! little-endian, other properties and elements skipped) and write occupied voxel centres
//! coloured by height (binary little-endian, `x y z` float and `red green blue` uchar).

use super::{Format, ParseError};

/// Read the vertex positions of a PLY file.
pub fn parse(bytes: &[u8]) -> Result<Vec<[f32; 3]>, ParseError> {
    parse_ply(bytes).map_err(ParseError::new(Format::Ply))
}

fn parse_ply(bytes: &[u8]) -> Result<Vec<[f32; 3]>, String> {
    let mut pos = 0;
    let mut lines = Vec::new();
    loop {
        let rest = &bytes[pos..];
        let n = rest
            .iter()
            .take(4096)
            .position(|&b| b == b'\n')
            .ok_or("header ends without end_header (or a line is longer than 4096 bytes)")?;
        let line = std::str::from_utf8(&rest[..n])
            .map_err(|_| "header is not text")?
            .trim()
            .to_string();
        pos += n + 1;
        if line == "end_header" {
            break;
        }
        lines.push(line);
        if lines.len() > 1000 {
            return Err("header longer than 1000 lines".into());
        }
    }
    if lines.first().map(String::as_str) != Some("ply") {
        return Err("first line is not 'ply'".into());
    }
    let mut format = None;
    let mut elements: Vec<Element> = Vec::new();
    for l in &lines[1..] {
        let w: Vec<&str> = l.split_whitespace().collect();
        match w.as_slice() {
            ["format", f, "1.0"] => format = Some(f.to_string()),
            ["format", _, v] => return Err(format!("unsupported PLY version '{v}' (1.0 is)")),
            ["comment", ..] | ["obj_info", ..] | [] => {}
            ["element", name, count] => {
                let count = count
                    .parse()
                    .map_err(|_| format!("element {name} has a bad count '{count}'"))?;
                elements.push((name.to_string(), count, Vec::new()));
            }
            ["property", "list", ..] => {
                let e = elements.last_mut().ok_or("property before any element")?;
                if e.0 == "vertex" {
                    return Err("list properties in the vertex element are not supported".into());
                }
                e.2.push(("list".into(), Scalar::List));
            }
            ["property", ty, name] => {
                let e = elements.last_mut().ok_or("property before any element")?;
                let s = Scalar::parse(ty).ok_or_else(|| format!("unknown property type '{ty}'"))?;
                e.2.push((name.to_string(), s));
            }
            _ => return Err(format!("unexpected header line '{l}'")),
        }
    }
    let binary = match format.as_deref() {
        Some("ascii") => false,
        Some("binary_little_endian") => true,
        Some(f) => {
            return Err(format!(
                "format {f} is not supported (ascii, binary_little_endian)"
            ))
        }
        None => return Err("no format line".into()),
    };
    let vi = elements
        .iter()
        .position(|e| e.0 == "vertex")
        .ok_or("no vertex element")?;
    if elements[..vi].iter().any(|e| e.1 > 0) {
        return Err("elements before vertex are not supported".into());
    }
    let (_, count, props) = &elements[vi];
    let find = |n: &str| {
        props
            .iter()
            .position(|p| p.0 == n)
            .ok_or_else(|| format!("vertex has no '{n}' property"))
    };
    let xyz = [find("x")?, find("y")?, find("z")?];
    if xyz
        .iter()
        .any(|&i| !matches!(props[i].1, Scalar::F32 | Scalar::F64))
    {
        return Err("x y z must be float or double".into());
    }
    let body = &bytes[pos..];
    if binary {
        let offs: Vec<usize> = props
            .iter()
            .scan(0, |o, p| {
                let at = *o;
                *o += p.1.size();
                Some(at)
            })
            .collect();
        let stride: usize = props.iter().map(|p| p.1.size()).sum();
        let need = count.checked_mul(stride).ok_or("vertex count overflows")?;
        if body.len() < need {
            return Err(format!(
                "data truncated: {count} vertices of {stride} bytes need {need}, file has {}",
                body.len()
            ));
        }
        Ok(body[..need]
            .chunks_exact(stride)
            .map(|r| xyz.map(|i| props[i].1.read_le(&r[offs[i]..]) as f32))
            .collect())
    } else {
        let text = std::str::from_utf8(body).map_err(|_| "ascii data is not text")?;
        // A vertex takes at least two bytes of text ("0\n"): reserve no more than fit.
        let mut out = Vec::with_capacity((*count).min(body.len() / 2));
        let mut rows = text.lines().filter(|l| !l.trim().is_empty());
        for n in 0..*count {
            let row = rows
                .next()
                .ok_or_else(|| format!("data truncated: {n} of {count} vertices"))?;
            let v: Vec<&str> = row.split_whitespace().collect();
            if v.len() < props.len() {
                return Err(format!(
                    "vertex {n} has {} values, expected {}",
                    v.len(),
                    props.len()
                ));
            }
            let mut p = [0f32; 3];
            for (k, &i) in xyz.iter().enumerate() {
                p[k] = v[i]
                    .parse()
                    .map_err(|_| format!("vertex {n}: '{}' is not a number", v[i]))?;
            }
            out.push(p);
        }
        Ok(out)
    }
}

/// A header element: name, count, properties (name, type).
type Element = (String, usize, Vec<(String, Scalar)>);

#[derive(Clone, Copy, Debug, PartialEq)]
enum Scalar {
    I8,
    U8,
    I16,
    U16,
    I32,
    U32,
    F32,
    F64,
    List,
}

impl Scalar {
    fn parse(t: &str) -> Option<Self> {
        Some(match t {
            "char" | "int8" => Self::I8,
            "uchar" | "uint8" => Self::U8,
            "short" | "int16" => Self::I16,
            "ushort" | "uint16" => Self::U16,
            "int" | "int32" => Self::I32,
            "uint" | "uint32" => Self::U32,
            "float" | "float32" => Self::F32,
            "double" | "float64" => Self::F64,
            _ => return None,
        })
    }

    fn size(self) -> usize {
        match self {
            Self::I8 | Self::U8 => 1,
            Self::I16 | Self::U16 => 2,
            Self::I32 | Self::U32 | Self::F32 => 4,
            Self::F64 => 8,
            Self::List => 0,
        }
    }

    fn read_le(self, b: &[u8]) -> f64 {
        match self {
            Self::F32 => f32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f64,
            Self::F64 => f64::from_le_bytes(b[..8].try_into().unwrap_or([0; 8])),
            _ => 0.0,
        }
    }
}

/// Colour for a height fraction `t` in [0, 1]: blue (low) through green to red (high).
pub fn height_color(t: f64) -> [u8; 3] {
    let t = if t.is_finite() {
        t.clamp(0.0, 1.0)
    } else {
        0.0
    };
    // Piecewise-linear blue -> cyan -> green -> yellow -> red.
    let stops = [
        [40.0, 60.0, 220.0],
        [0.0, 200.0, 220.0],
        [40.0, 200.0, 60.0],
        [240.0, 220.0, 40.0],
        [220.0, 50.0, 40.0],
    ];
    let x = t * (stops.len() - 1) as f64;
    let i = (x.floor() as usize).min(stops.len() - 2);
    let f = x - i as f64;
    std::array::from_fn(|c| (stops[i][c] * (1.0 - f) + stops[i + 1][c] * f).round() as u8)
}

/// Encode points with colours as binary little-endian PLY.
pub fn encode_colored(points: &[([f32; 3], [u8; 3])]) -> Vec<u8> {
    let mut out = format!(
        "ply\nformat binary_little_endian 1.0\ncomment written by voxmap: occupied voxel centres\n\
         element vertex {}\nproperty float x\nproperty float y\nproperty float z\n\
         property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n",
        points.len()
    )
    .into_bytes();
    out.reserve(points.len() * 15);
    for (p, c) in points {
        for v in p {
            out.extend_from_slice(&v.to_le_bytes());
        }
        out.extend_from_slice(c);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn binary_round_trip_and_truncation() {
        let pts = vec![([1.0, -2.5, 3.25], [1, 2, 3]), ([0.0, 0.0, 1e6], [9, 9, 9])];
        let b = encode_colored(&pts);
        assert_eq!(parse(&b).unwrap(), vec![[1.0, -2.5, 3.25], [0.0, 0.0, 1e6]]);
        assert!(parse(&b[..b.len() - 1])
            .unwrap_err()
            .problem
            .contains("truncated"));
    }

    #[test]
    fn ascii_with_extra_properties_and_faces() {
        let t = "ply\nformat ascii 1.0\nelement vertex 2\nproperty float nx\nproperty float x\n\
                 property float y\nproperty double z\nelement face 1\nproperty list uchar int vertex_indices\n\
                 end_header\n9 1 2 3\n9 4 5 6.5\n3 0 1 1\n";
        assert_eq!(
            parse(t.as_bytes()).unwrap(),
            vec![[1.0, 2.0, 3.0], [4.0, 5.0, 6.5]]
        );
    }

    #[test]
    fn bad_files_say_why() {
        let cases: [(&str, &str); 7] = [
            ("ply\nformat ascii 2.0\nelement vertex 0\nend_header\n", "version"),
            ("ply\nformat ascii 1.0\nelement vertex 999999999\nproperty float x\nproperty float y\nproperty float z\nend_header\n1 2 3\n", "truncated"),
            ("plx\nformat ascii 1.0\nend_header\n", "first line"),
            ("ply\nformat binary_big_endian 1.0\nelement vertex 0\nend_header\n", "not supported"),
            ("ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nend_header\n1 2\n", "no 'z'"),
            ("ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\nend_header\n1 2 3\n", "truncated"),
            ("ply\nformat ascii 1.0\nelement vertex 1\nproperty int x\nproperty float y\nproperty float z\nend_header\n1 2 3\n", "float or double"),
        ];
        for (text, why) in cases {
            let e = parse(text.as_bytes()).unwrap_err();
            assert!(e.problem.contains(why), "{e} should mention {why}");
            assert_eq!(e.format, Format::Ply);
        }
        assert!(parse(b"ply\nformat ascii 1.0\n").is_err());
    }

    #[test]
    fn height_colors_run_blue_to_red() {
        assert_eq!(height_color(0.0), [40, 60, 220]);
        assert_eq!(height_color(1.0), [220, 50, 40]);
        assert_eq!(height_color(f64::NAN), height_color(0.0));
        assert_eq!(height_color(7.0), height_color(1.0));
    }
}

//! Recorded scans without an embedded pose: KITTI-style `.bin` scans (float32 `x y z
//! intensity` records) and the pose files that go with them, KITTI odometry (12 numbers
//! per line: a 3x4 row-major `[R | t]`) or TUM (`t tx ty tz qx qy qz qw`).

use super::{Format, ParseError};
use nalgebra::{Isometry3, Matrix3, Quaternion, Rotation3, Translation3, UnitQuaternion};

/// Points of a KITTI `.bin` scan.
pub fn parse_kitti_bin(bytes: &[u8]) -> Result<Vec<[f32; 3]>, ParseError> {
    kitti_bin(bytes).map_err(ParseError::new(Format::KittiBin))
}

fn kitti_bin(bytes: &[u8]) -> Result<Vec<[f32; 3]>, String> {
    if !bytes.len().is_multiple_of(16) {
        return Err(format!(
            "{} bytes is not a whole number of 16-byte (x y z intensity) records",
            bytes.len()
        ));
    }
    Ok(bytes
        .chunks_exact(16)
        .map(|r| {
            std::array::from_fn(|k| {
                f32::from_le_bytes(r[4 * k..4 * k + 4].try_into().unwrap_or([0; 4]))
            })
        })
        .collect())
}

/// One pose of a pose file, with its timestamp when the file has them (TUM).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct StampedPose {
    pub stamp: Option<f64>,
    pub pose: Isometry3<f64>,
}

/// Parse a KITTI or TUM pose file (told apart by the count of numbers on a line; `#`
/// starts a comment). Rotations must be orthonormal and quaternions unit length to 1e-3.
pub fn parse_poses(text: &str) -> Result<Vec<StampedPose>, ParseError> {
    poses(text).map_err(ParseError::new(Format::Poses))
}

fn poses(text: &str) -> Result<Vec<StampedPose>, String> {
    let mut out = Vec::new();
    for (n, line) in text.lines().enumerate() {
        let line = line.split('#').next().unwrap_or("").trim();
        if line.is_empty() {
            continue;
        }
        let v: Vec<f64> = line
            .split_whitespace()
            .map(|w| w.parse::<f64>())
            .collect::<Result<_, _>>()
            .map_err(|_| format!("line {}: not all numbers", n + 1))?;
        if v.iter().any(|x| !x.is_finite()) {
            return Err(format!("line {}: non-finite number", n + 1));
        }
        let p = match v.len() {
            12 => {
                let r = Matrix3::new(v[0], v[1], v[2], v[4], v[5], v[6], v[8], v[9], v[10]);
                if (r.transpose() * r - Matrix3::identity()).abs().max() > 1e-3
                    || r.determinant() < 0.0
                {
                    return Err(format!("line {}: rotation is not orthonormal", n + 1));
                }
                let q = UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(r));
                StampedPose {
                    stamp: None,
                    pose: Isometry3::from_parts(Translation3::new(v[3], v[7], v[11]), q),
                }
            }
            8 => {
                let q = Quaternion::new(v[7], v[4], v[5], v[6]);
                if (q.norm() - 1.0).abs() > 1e-3 {
                    return Err(format!("line {}: quaternion is not unit length", n + 1));
                }
                StampedPose {
                    stamp: Some(v[0]),
                    pose: Isometry3::from_parts(
                        Translation3::new(v[1], v[2], v[3]),
                        UnitQuaternion::from_quaternion(q),
                    ),
                }
            }
            k => {
                return Err(format!(
                    "line {}: {k} numbers; a KITTI pose has 12, a TUM pose 8",
                    n + 1
                ))
            }
        };
        if out
            .first()
            .is_some_and(|f: &StampedPose| f.stamp.is_some() != p.stamp.is_some())
        {
            return Err(format!(
                "line {}: KITTI and TUM poses mixed in one file",
                n + 1
            ));
        }
        out.push(p);
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn kitti_bin_records() {
        let mut b = Vec::new();
        for v in [1.0f32, 2.0, 3.0, 0.5, -1.0, -2.0, -3.0, 0.1] {
            b.extend_from_slice(&v.to_le_bytes());
        }
        assert_eq!(
            parse_kitti_bin(&b).unwrap(),
            vec![[1.0, 2.0, 3.0], [-1.0, -2.0, -3.0]]
        );
        assert!(parse_kitti_bin(&b[..20])
            .unwrap_err()
            .problem
            .contains("16-byte"));
    }

    #[test]
    fn kitti_and_tum_poses() {
        let kitti = "1 0 0 5  0 0 -1 6  0 1 0 7\n# comment\n\n1 0 0 0 0 1 0 0 0 0 1 0\n";
        let p = parse_poses(kitti).unwrap();
        assert_eq!(p.len(), 2);
        assert_eq!(p[0].stamp, None);
        let x = p[0].pose * nalgebra::Point3::new(0.0, 1.0, 0.0);
        assert!((x - nalgebra::Point3::new(5.0, 6.0, 8.0)).norm() < 1e-9);
        let tum = "1311877813.99 1 2 3 0 0 0.7071068 0.7071068\n";
        let p = parse_poses(tum).unwrap();
        assert_eq!(p[0].stamp, Some(1311877813.99));
        let x = p[0].pose * nalgebra::Point3::new(1.0, 0.0, 0.0);
        assert!((x - nalgebra::Point3::new(1.0, 3.0, 3.0)).norm() < 1e-6);
    }

    #[test]
    fn bad_pose_lines() {
        for (t, why) in [
            ("1 2 3\n", "12"),
            ("1 0 0 0 0 2 0 0 0 0 1 0\n", "orthonormal"),
            ("0 1 2 3 0 0 0 2\n", "unit"),
            ("0 1 2 3 0 0 x 1\n", "numbers"),
            ("0 1 2 NaN 0 0 0 1\n", "non-finite"),
            ("0 1 2 3 0 0 0 1\n1 0 0 0 0 1 0 0 0 0 1 0\n", "mixed"),
        ] {
            let e = parse_poses(t).unwrap_err();
            assert!(e.problem.contains(why), "{e}");
        }
    }
}

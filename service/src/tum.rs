//! The TUM RGB-D benchmark's depth frames (a folder with `depth/<stamp>.png`, 16-bit, 5000
//! units per metre, and an association file of `rgb depth tx ty tz qx qy qz qw` lines):
//! back-projected with TUM's intrinsics for registered depth, posed from the file.

use anyhow::{bail, Context, Result};
use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion};
use std::path::Path;

/// One depth frame: its stamp (as the file names it), the optical frame's pose in the
/// world, and the points in the optical frame (x right, y down, z forward).
pub struct DepthFrame {
    pub stamp: String,
    pub pose: Isometry3<f64>,
    pub points: Vec<[f32; 3]>,
}

/// Every depth image of `dir` that the association file `assoc` poses, in stamp order.
pub fn read_frames(dir: &Path, assoc: &str) -> Result<Vec<DepthFrame>> {
    let text = std::fs::read_to_string(dir.join(assoc))
        .with_context(|| format!("reading {}", dir.join(assoc).display()))?;
    let mut poses = std::collections::HashMap::new();
    for l in text.lines().filter(|l| !l.starts_with('#')) {
        let w: Vec<&str> = l.split_whitespace().collect();
        if w.len() != 9 {
            continue;
        }
        let v: Vec<f64> = w[2..].iter().filter_map(|s| s.parse().ok()).collect();
        if v.len() != 7 {
            bail!("{assoc}: bad pose line {l:?}");
        }
        let q = UnitQuaternion::from_quaternion(Quaternion::new(v[6], v[3], v[4], v[5]));
        let depth = w[1].trim_start_matches("depth/").trim_end_matches(".png");
        poses.insert(
            depth.to_string(),
            Isometry3::from_parts(Translation3::new(v[0], v[1], v[2]), q),
        );
    }
    let mut names: Vec<String> = std::fs::read_dir(dir.join("depth"))
        .with_context(|| format!("reading {}", dir.join("depth").display()))?
        .filter_map(|e| e.ok())
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .filter(|n| n.ends_with(".png"))
        .collect();
    names.sort();
    let mut out = Vec::new();
    for n in names {
        let stamp = n.trim_end_matches(".png").to_string();
        let Some(&pose) = poses.get(&stamp) else {
            continue;
        };
        let path = dir.join("depth").join(&n);
        let points = depth_points(&path).with_context(|| path.display().to_string())?;
        out.push(DepthFrame {
            stamp,
            pose,
            points,
        });
    }
    Ok(out)
}

/// A 16-bit depth PNG back-projected: fx = fy = 525, cx = 319.5, cy = 239.5; 0 = none.
fn depth_points(path: &Path) -> Result<Vec<[f32; 3]>> {
    let dec = png::Decoder::new(std::io::BufReader::new(std::fs::File::open(path)?));
    let mut r = dec.read_info()?;
    let mut buf = vec![0; r.output_buffer_size().context("image too large")?];
    let info = r.next_frame(&mut buf)?;
    if info.bit_depth != png::BitDepth::Sixteen || info.color_type != png::ColorType::Grayscale {
        bail!("not a 16-bit grey depth image");
    }
    let (w, h) = (info.width as usize, info.height as usize);
    let mut points = Vec::new();
    for v in 0..h {
        for u in 0..w {
            let d = u16::from_be_bytes([buf[2 * (v * w + u)], buf[2 * (v * w + u) + 1]]);
            if d == 0 {
                continue;
            }
            let z = f64::from(d) / 5000.0;
            points.push([
                ((u as f64 - 319.5) * z / 525.0) as f32,
                ((v as f64 - 239.5) * z / 525.0) as f32,
                z as f32,
            ]);
        }
    }
    Ok(points)
}

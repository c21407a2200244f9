//! `voxmap render`: PNG pictures of a map, snapshot or `.bt` file: a top-down view
//! (occupied coloured by height, free and unknown distinct) or a horizontal slice, with a
//! scale bar, a legend and a caption.

use crate::files::Loaded;
use anyhow::{bail, Context, Result};
use clap::Args;
use std::path::{Path, PathBuf};
use voxmap_map::coord::MAX_VOXEL_INDEX;
use voxmap_map::grid::voxel_at;
use voxmap_map::io::ply::height_color;
use voxmap_map::LeafOccupancy;

#[derive(Args, Debug)]
pub struct RenderArgs {
    /// Map file, snapshot file or OctoMap .bt file.
    pub input: PathBuf,
    /// PNG to write.
    #[arg(short, long)]
    pub out: PathBuf,
    /// Draw the horizontal slice at this height (metres) instead of the top-down view.
    #[arg(long)]
    pub slice: Option<f64>,
    /// Top-down view: only voxels with centres between these heights (metres), e.g. to
    /// look under a ceiling.
    #[arg(long, num_args = 2, value_names = ["MIN", "MAX"], allow_negative_numbers = true)]
    pub z_range: Option<Vec<f64>>,
    /// Longest side of the map area, pixels.
    #[arg(long, default_value_t = 1000)]
    pub size: u32,
    /// With --slice: colour the free voxels by their distance to the nearest obstacle
    /// (the file's distance field, or one built from a map file with
    /// --esdf-max-distance and --esdf-unknown).
    #[arg(long, requires = "slice")]
    pub distance: bool,
    /// With --distance, for a map file without a field of these settings: the max
    /// distance (metres).
    #[arg(long, default_value_t = 2.0)]
    pub esdf_max_distance: f64,
    /// With --distance: what unknown voxels count as, free or occupied.
    #[arg(long, default_value = "free")]
    pub esdf_unknown: voxmap_map::field::UnknownPolicy,
}

pub fn run(a: RenderArgs) -> Result<()> {
    let loaded = Loaded::read(&a.input)?;
    let view = match (a.slice, a.z_range.as_deref()) {
        (Some(z), _) if !z.is_finite() => bail!("--slice must be a finite height"),
        (Some(z), _) => View::Slice(z),
        (None, Some(&[lo, hi])) if !(lo.is_finite() && hi.is_finite() && lo <= hi) => {
            bail!("--z-range needs finite MIN <= MAX, not {lo} {hi}")
        }
        (None, r) => View::Top(r.map(|r| (r[0], r[1]))),
    };
    let img = if a.distance {
        let cfg = voxmap_map::field::FieldConfig {
            max_distance: a.esdf_max_distance,
            unknown: a.esdf_unknown,
            window: None,
        };
        let bytes = voxmap_map::io::mapfile::read_as_snapshot_with_field(&a.input, &cfg)?;
        let snap = voxmap_map::snapshot::SnapshotView::open(&bytes)?;
        let field = snap.distance_field().with_context(|| {
            format!(
                "{}: no distance field (give a map file, or a snapshot that carries one)",
                a.input.display()
            )
        })?;
        render_with(
            &loaded.leaves,
            loaded.resolution,
            view,
            a.size,
            Some(&field),
        )?
    } else {
        render(&loaded.leaves, loaded.resolution, view, a.size)?
    };
    img.write_png(&a.out)?;
    println!(
        "wrote {} ({} x {} px)",
        a.out.display(),
        img.width,
        img.height
    );
    Ok(())
}

#[derive(Clone, Copy, Debug)]
pub enum View {
    /// Top-down, optionally within a height band (metres).
    Top(Option<(f64, f64)>),
    /// The layer of voxels holding this height (metres).
    Slice(f64),
}

/// An RGB image.
pub struct Image {
    pub width: usize,
    pub height: usize,
    pub rgb: Vec<u8>,
}

const UNKNOWN: [u8; 3] = [150, 150, 158];
const FREE: [u8; 3] = [250, 250, 250];
const SLICE_OCCUPIED: [u8; 3] = [20, 20, 20];
const PAPER: [u8; 3] = [255, 255, 255];
const INK: [u8; 3] = [0, 0, 0];
const CAPTION_H: usize = 64;
const MIN_WIDTH: usize = 560;

impl Image {
    fn new(width: usize, height: usize, fill: [u8; 3]) -> Self {
        Self {
            width,
            height,
            rgb: fill.repeat(width * height),
        }
    }

    #[cfg(test)]
    pub fn pixel(&self, x: usize, y: usize) -> [u8; 3] {
        let i = 3 * (y * self.width + x);
        [self.rgb[i], self.rgb[i + 1], self.rgb[i + 2]]
    }

    fn fill(&mut self, x0: usize, y0: usize, w: usize, h: usize, c: [u8; 3]) {
        for y in y0..(y0 + h).min(self.height) {
            for x in x0..(x0 + w).min(self.width) {
                let i = 3 * (y * self.width + x);
                self.rgb[i..i + 3].copy_from_slice(&c);
            }
        }
    }

    /// Draw `text` at (x, y) with the 5x7 font scaled by `s`; returns the end x.
    fn text(&mut self, x: usize, y: usize, s: usize, text: &str) -> usize {
        let mut cx = x;
        for ch in text.chars() {
            let g = glyph(ch);
            for (row, bits) in g.iter().enumerate() {
                for col in 0..5 {
                    if bits >> (4 - col) & 1 != 0 {
                        self.fill(cx + col * s, y + row * s, s, s, INK);
                    }
                }
            }
            cx += 6 * s;
        }
        cx
    }

    pub fn write_png(&self, path: &Path) -> Result<()> {
        let f =
            std::fs::File::create(path).with_context(|| format!("creating {}", path.display()))?;
        let mut enc = png::Encoder::new(
            std::io::BufWriter::new(f),
            self.width as u32,
            self.height as u32,
        );
        enc.set_color(png::ColorType::Rgb);
        enc.set_depth(png::BitDepth::Eight);
        let mut w = enc.write_header().context("writing PNG header")?;
        w.write_image_data(&self.rgb).context("writing PNG data")?;
        w.finish().context("finishing PNG")?;
        Ok(())
    }
}

/// Render leaves at `res` metres per voxel; the map area's longer side is about `size` px.
pub fn render(leaves: &[LeafOccupancy], res: f64, view: View, size: u32) -> Result<Image> {
    render_with(leaves, res, view, size, None)
}

/// [`render`], a slice's free voxels coloured by `field`'s distance when given.
pub fn render_with(
    leaves: &[LeafOccupancy],
    res: f64,
    view: View,
    size: u32,
    field: Option<&voxmap_map::snapshot::FieldView<'_>>,
) -> Result<Image> {
    let mut lo = [i32::MAX; 3];
    let mut hi = [i32::MIN; 3];
    for l in leaves {
        for i in l.known.iter_ones() {
            let v = voxel_at(l.origin, i).to_array();
            for k in 0..3 {
                lo[k] = lo[k].min(v[k]);
                hi[k] = hi[k].max(v[k]);
            }
        }
    }
    if lo[0] > hi[0] {
        bail!("the map is empty: nothing to draw");
    }
    let (w, h) = ((hi[0] - lo[0] + 1) as usize, (hi[1] - lo[1] + 1) as usize);
    let size = size.clamp(64, 8192) as usize;
    // Voxels per cell (cells are square in pixels), then pixels per cell.
    let k = w.max(h).div_ceil(size).max(1);
    let (cw, ch) = (w.div_ceil(k), h.div_ceil(k));
    let px = (size / cw.max(ch)).clamp(1, 16);
    // Per cell: highest occupied z (top) or occupancy at the slice layer, and known-ness.
    let mut top = vec![i32::MIN; cw * ch];
    let mut known = vec![false; cw * ch];
    // Per cell: the smallest distance of its free voxels, with a field.
    let mut nearest = vec![f64::INFINITY; cw * ch];
    // Heights far outside the map clamp to the index space, where `zhi + 1` cannot overflow.
    let layer = |z: f64| (z / res).floor().clamp(-MAX_VOXEL_INDEX, MAX_VOXEL_INDEX) as i32;
    let (zlo, zhi) = match view {
        View::Top(Some((a, b))) => (layer(a), layer(b)),
        View::Top(None) => (lo[2], hi[2]),
        View::Slice(z) => (layer(z), layer(z)),
    };
    for l in leaves {
        if l.origin.z + 7 < zlo || l.origin.z > zhi {
            continue;
        }
        for i in l.known.iter_ones() {
            let v = voxel_at(l.origin, i).to_array();
            if v[2] < zlo || v[2] > zhi {
                continue;
            }
            let c = ((v[1] - lo[1]) as usize / k) * cw + (v[0] - lo[0]) as usize / k;
            known[c] = true;
            if l.occupied.get(i) {
                top[c] = top[c].max(v[2]);
            } else if let Some(d) = field.and_then(|f| f.distance(voxel_at(l.origin, i))) {
                nearest[c] = nearest[c].min(d);
            }
        }
    }
    let (mut zmin, mut zmax) = (i32::MAX, i32::MIN);
    for &z in top.iter().filter(|&&z| z != i32::MIN) {
        zmin = zmin.min(z);
        zmax = zmax.max(z);
    }
    let map_w = cw * px;
    let width = map_w.max(MIN_WIDTH);
    let mut img = Image::new(width, ch * px + CAPTION_H, PAPER);
    for cy in 0..ch {
        for cx in 0..cw {
            let c = cy * cw + cx;
            let color = match (top[c], known[c], view) {
                (z, _, View::Top(_)) if z != i32::MIN => {
                    height_color((z - zmin) as f64 / (zmax - zmin).max(1) as f64)
                }
                (z, _, View::Slice(_)) if z != i32::MIN => SLICE_OCCUPIED,
                (_, true, _) if nearest[c].is_finite() => {
                    // Near obstacles red, at the max distance blue (reversed height ramp).
                    let max = field.map_or(1.0, |f| f.max_distance());
                    height_color(1.0 - (nearest[c] / max).clamp(0.0, 1.0))
                }
                (_, true, _) => FREE,
                _ => UNKNOWN,
            };
            // +y is up in the picture.
            img.fill(cx * px, (ch - 1 - cy) * px, px, px, color);
        }
    }
    // Caption band: scale bar, legend, caption.
    let y0 = ch * px + 8;
    let metres_per_px = res * k as f64 / px as f64;
    let bar_m = nice_length(metres_per_px * map_w as f64 / 4.0);
    let bar_px = ((bar_m / metres_per_px).round() as usize).max(1);
    img.fill(8, y0 + 6, bar_px, 4, INK);
    img.fill(8, y0, 2, 16, INK);
    img.fill(8 + bar_px - 2, y0, 2, 16, INK);
    let x = img.text(16 + bar_px, y0 + 1, 2, &format!("{} M", fmt_m(bar_m)));
    let mut x = x + 16;
    let swatches: Vec<([u8; 3], &str)> = match view {
        View::Top(_) => vec![
            (height_color(0.0), "LOW"),
            (height_color(1.0), "HIGH"),
            (FREE, "FREE"),
            (UNKNOWN, "UNKNOWN"),
        ],
        View::Slice(_) if field.is_some() => vec![
            (SLICE_OCCUPIED, "OCCUPIED"),
            (height_color(1.0), "NEAR"),
            (height_color(0.0), "AT MAX"),
            (UNKNOWN, "UNKNOWN"),
        ],
        View::Slice(_) => vec![
            (SLICE_OCCUPIED, "OCCUPIED"),
            (FREE, "FREE"),
            (UNKNOWN, "UNKNOWN"),
        ],
    };
    for (c, name) in swatches {
        img.fill(x, y0, 14, 14, INK);
        img.fill(x + 1, y0 + 1, 12, 12, c);
        x = img.text(x + 18, y0 + 1, 2, name) + 10;
    }
    let what = match view {
        View::Top(_) => format!(
            "TOP-DOWN, Z {}..{} M",
            fmt_m(zlo as f64 * res),
            fmt_m((zhi + 1) as f64 * res)
        ),
        View::Slice(z) => match field {
            Some(f) => format!(
                "DISTANCE AT Z {} M, MAX {} M",
                fmt_m(z),
                fmt_m(f.max_distance())
            ),
            None => format!("SLICE AT Z {} M", fmt_m(z)),
        },
    };
    let caption = format!(
        "{what} | {} M VOXELS | {} X {} M",
        fmt_m(res),
        fmt_m(w as f64 * res),
        fmt_m(h as f64 * res)
    );
    img.text(8, y0 + 28, 2, &caption);
    Ok(img)
}

/// The largest 1, 2 or 5 times a power of ten not above `x`.
fn nice_length(x: f64) -> f64 {
    let p = 10f64.powf(x.max(1e-6).log10().floor());
    [5.0, 2.0, 1.0]
        .into_iter()
        .map(|m| m * p)
        .find(|&v| v <= x)
        .unwrap_or(p)
}

fn fmt_m(x: f64) -> String {
    let s = format!("{x:.2}");
    let s = s.trim_end_matches('0').trim_end_matches('.');
    if s == "-0" {
        "0".into()
    } else {
        s.to_string()
    }
}

/// 5x7 glyphs, one byte per row, bit 4 leftmost. Letters are upper case only.
fn glyph(c: char) -> [u8; 7] {
    match c.to_ascii_uppercase() {
        'A' => [0x0E, 0x11, 0x11, 0x1F, 0x11, 0x11, 0x11],
        'B' => [0x1E, 0x11, 0x11, 0x1E, 0x11, 0x11, 0x1E],
        'C' => [0x0E, 0x11, 0x10, 0x10, 0x10, 0x11, 0x0E],
        'D' => [0x1E, 0x11, 0x11, 0x11, 0x11, 0x11, 0x1E],
        'E' => [0x1F, 0x10, 0x10, 0x1E, 0x10, 0x10, 0x1F],
        'F' => [0x1F, 0x10, 0x10, 0x1E, 0x10, 0x10, 0x10],
        'G' => [0x0E, 0x11, 0x10, 0x17, 0x11, 0x11, 0x0F],
        'H' => [0x11, 0x11, 0x11, 0x1F, 0x11, 0x11, 0x11],
        'I' => [0x0E, 0x04, 0x04, 0x04, 0x04, 0x04, 0x0E],
        'J' => [0x07, 0x02, 0x02, 0x02, 0x02, 0x12, 0x0C],
        'K' => [0x11, 0x12, 0x14, 0x18, 0x14, 0x12, 0x11],
        'L' => [0x10, 0x10, 0x10, 0x10, 0x10, 0x10, 0x1F],
        'M' => [0x11, 0x1B, 0x15, 0x15, 0x11, 0x11, 0x11],
        'N' => [0x11, 0x11, 0x19, 0x15, 0x13, 0x11, 0x11],
        'O' => [0x0E, 0x11, 0x11, 0x11, 0x11, 0x11, 0x0E],
        'P' => [0x1E, 0x11, 0x11, 0x1E, 0x10, 0x10, 0x10],
        'Q' => [0x0E, 0x11, 0x11, 0x11, 0x15, 0x12, 0x0D],
        'R' => [0x1E, 0x11, 0x11, 0x1E, 0x14, 0x12, 0x11],
        'S' => [0x0F, 0x10, 0x10, 0x0E, 0x01, 0x01, 0x1E],
        'T' => [0x1F, 0x04, 0x04, 0x04, 0x04, 0x04, 0x04],
        'U' => [0x11, 0x11, 0x11, 0x11, 0x11, 0x11, 0x0E],
        'V' => [0x11, 0x11, 0x11, 0x11, 0x11, 0x0A, 0x04],
        'W' => [0x11, 0x11, 0x11, 0x15, 0x15, 0x15, 0x0A],
        'X' => [0x11, 0x11, 0x0A, 0x04, 0x0A, 0x11, 0x11],
        'Y' => [0x11, 0x11, 0x0A, 0x04, 0x04, 0x04, 0x04],
        'Z' => [0x1F, 0x01, 0x02, 0x04, 0x08, 0x10, 0x1F],
        '0' => [0x0E, 0x11, 0x13, 0x15, 0x19, 0x11, 0x0E],
        '1' => [0x04, 0x0C, 0x04, 0x04, 0x04, 0x04, 0x0E],
        '2' => [0x0E, 0x11, 0x01, 0x02, 0x04, 0x08, 0x1F],
        '3' => [0x1F, 0x02, 0x04, 0x02, 0x01, 0x11, 0x0E],
        '4' => [0x02, 0x06, 0x0A, 0x12, 0x1F, 0x02, 0x02],
        '5' => [0x1F, 0x10, 0x1E, 0x01, 0x01, 0x11, 0x0E],
        '6' => [0x06, 0x08, 0x10, 0x1E, 0x11, 0x11, 0x0E],
        '7' => [0x1F, 0x01, 0x02, 0x04, 0x08, 0x08, 0x08],
        '8' => [0x0E, 0x11, 0x11, 0x0E, 0x11, 0x11, 0x0E],
        '9' => [0x0E, 0x11, 0x11, 0x0F, 0x01, 0x02, 0x0C],
        '.' => [0, 0, 0, 0, 0, 0x0C, 0x0C],
        ',' => [0, 0, 0, 0, 0x0C, 0x04, 0x08],
        '-' => [0, 0, 0, 0x1F, 0, 0, 0],
        '+' => [0, 0x04, 0x04, 0x1F, 0x04, 0x04, 0],
        '=' => [0, 0, 0x1F, 0, 0x1F, 0, 0],
        ':' => [0, 0x0C, 0x0C, 0, 0x0C, 0x0C, 0],
        '|' => [0x04; 7],
        '/' => [0x01, 0x02, 0x02, 0x04, 0x08, 0x08, 0x10],
        '(' => [0x02, 0x04, 0x08, 0x08, 0x08, 0x04, 0x02],
        ')' => [0x08, 0x04, 0x02, 0x02, 0x02, 0x04, 0x08],
        _ => [0; 7],
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use voxmap_map::mask::Mask512;
    use voxmap_map::VoxelCoord;

    /// A 4 m x 2 m floor of free voxels with one occupied wall column at x = 1 m.
    fn room() -> Vec<LeafOccupancy> {
        let mut leaves = Vec::new();
        for lx in 0..5 {
            for ly in 0..3 {
                let mut l = LeafOccupancy {
                    origin: VoxelCoord::new(lx * 8, ly * 8, 0),
                    known: Mask512::EMPTY,
                    occupied: Mask512::EMPTY,
                };
                for i in 0..64 {
                    l.known.set(i);
                    let x = lx * 8 + (i & 7) as i32;
                    if x == 10 {
                        l.occupied.set(i);
                    }
                }
                leaves.push(l);
            }
        }
        leaves
    }

    #[test]
    fn top_down_shows_wall_free_floor_and_unknown_margin() {
        let img = render(&room(), 0.1, View::Top(None), 400).unwrap();
        // 40 x 24 voxels at 10 px each; the caption band below.
        assert_eq!(img.width, 560);
        assert_eq!(img.height, 240 + CAPTION_H);
        assert_eq!(img.pixel(10 * 10 + 5, 5), height_color(0.0));
        assert_eq!(img.pixel(5, 5), FREE);
        assert_eq!(img.pixel(9 * 10 + 5, 235), FREE);
        // Beyond the map's width, before the caption: paper.
        assert_eq!(img.pixel(500, 5), PAPER);
        // A slice through the floor layer sees the wall; one above it sees unknown.
        let s = render(&room(), 0.1, View::Slice(0.05), 400).unwrap();
        assert_eq!(s.pixel(105, 5), SLICE_OCCUPIED);
        let s = render(&room(), 0.1, View::Slice(0.15), 400).unwrap();
        assert_eq!(s.pixel(105, 5), UNKNOWN);
        assert!(render(&[], 0.1, View::Top(None), 400).is_err());
    }

    #[test]
    fn a_distance_slice_colours_free_voxels_by_their_distance() {
        use voxmap_map::field::{DistanceField, FieldConfig};
        use voxmap_map::snapshot::{Meta, Plan, Scope, SnapshotView};
        use voxmap_map::{OccupancyMap, SensorModel};
        // The same room as a map: the wall at x = 1 m, free floor elsewhere.
        let mut map = OccupancyMap::new(0.1, SensorModel::default()).unwrap();
        for l in room() {
            for i in l.known.iter_ones() {
                let v = voxel_at(l.origin, i);
                map.set_value(v, if l.occupied.get(i) { 100 } else { -100 });
            }
        }
        let mut f = DistanceField::new(FieldConfig::default(), 0.1).unwrap();
        f.rebuild(&map, None);
        let bytes = Plan::new(&map, Scope::Whole, Meta::default())
            .with_field(&f)
            .to_vec();
        let snap = SnapshotView::open(&bytes).unwrap();
        let field = snap.distance_field().unwrap();
        let img = render_with(&room(), 0.1, View::Slice(0.05), 400, Some(&field)).unwrap();
        assert_eq!(img.pixel(105, 5), SLICE_OCCUPIED);
        // Next to the wall (0.1 m): near the ramp's near end; 2.5 m away: at the max.
        assert_eq!(img.pixel(115, 5), height_color(1.0 - 0.05));
        assert_eq!(img.pixel(355, 5), height_color(0.0));
    }

    #[test]
    fn scale_bar_lengths_are_round() {
        assert_eq!(nice_length(0.9), 0.5);
        assert_eq!(nice_length(3.7), 2.0);
        assert_eq!(nice_length(10.0), 10.0);
        assert_eq!(fmt_m(0.1), "0.1");
        assert_eq!(fmt_m(2.0), "2");
    }
}

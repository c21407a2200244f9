//! OctoMap's binary tree format (`.bt`): maximum-likelihood occupancy (occupied / free /
//! unknown) in an octree of depth 16, as OctoMap's `OcTree::writeBinary` writes it and its
//! tools (octovis, `bt2vrml`, `convert_octree`, `edit_octree`) read it.
//!
//! ```text
//! # Octomap OcTree binary file      text header lines, each ending in '\n'
//! id OcTree
//! size <nodes in the tree, root included>
//! res <voxel edge, metres>
//! data
//! <root node>                       then the tree, depth first
//! ```
//! A node is two bytes, 2 bits per child `c` in `0..8` (children 0-3 in the first byte,
//! 4-7 in the second, child `c % 4` at bits `2(c%4)`, `2(c%4)+1`): `00` no child
//! (unknown), `01` free leaf, `10` occupied leaf, `11` inner node; then the inner children's
//! nodes in child order. Child `c` of a node at depth `d` holds the keys whose bit `15-d`
//! is `c & 1` (x), `c >> 1 & 1` (y), `c >> 2 & 1` (z). A voxel's key is its index plus
//! 32768, so OctoMap's voxel `floor(p / res)` is exactly ours and the exported map covers
//! indices `-32768..=32767` on each axis.
//!
//! The writer prunes as OctoMap does: eight known children of one state become one leaf.

use crate::coord::VoxelCoord;
use crate::mask::Mask512;
use crate::occupancy::LeafOccupancy;

const HEADER_LINE: &str = "# Octomap OcTree binary file";
/// Tree depth: leaves at depth 16 are voxels.
const DEPTH: u32 = 16;
/// Depth of the nodes that are exactly our 8x8x8 leaves.
const LEAF_DEPTH: u32 = DEPTH - 3;
const KEY_OFFSET: i32 = 1 << (DEPTH - 1);

/// An OctoMap file could not be written or read.
#[derive(Debug, Clone, PartialEq)]
pub enum BtError {
    /// A known voxel lies outside OctoMap's 16-bit key space.
    OutOfRange { origin: VoxelCoord },
    /// A leaf origin is not a multiple of 8 (corrupt input).
    Unaligned { origin: VoxelCoord },
    /// Two leaves share an origin (corrupt input).
    Duplicate { origin: VoxelCoord },
    /// The bytes are not a valid `.bt` file.
    Format(String),
}

impl std::fmt::Display for BtError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::OutOfRange { origin } => write!(
                f,
                "leaf at voxel {origin:?} lies outside OctoMap's key space (voxel indices -32768..=32767)"
            ),
            Self::Unaligned { origin } => write!(f, "leaf origin {origin:?} is not a multiple of 8"),
            Self::Duplicate { origin } => write!(f, "two leaves at origin {origin:?}"),
            Self::Format(m) => write!(f, "not a valid OctoMap .bt file: {m}"),
        }
    }
}

impl std::error::Error for BtError {}

/// Maximum-likelihood state of a node's whole cube.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
enum Summary {
    /// Nothing known: no child is written.
    Empty,
    Free,
    Occupied,
    /// Anything else: an inner node whose bytes are in the output.
    Mixed,
}

impl Summary {
    fn code(self) -> u8 {
        match self {
            Summary::Empty => 0b00,
            Summary::Free => 0b01,
            Summary::Occupied => 0b10,
            Summary::Mixed => 0b11,
        }
    }
}

struct Writer {
    out: Vec<u8>,
    nodes: u64,
}

impl Writer {
    /// Write an inner node whose child `c` is produced (its subtree written) by
    /// `child(self, c)`. A node whose eight children are leaves of one state collapses
    /// into that state and leaves nothing in the output, unless `keep` (the root).
    fn inner(&mut self, keep: bool, mut child: impl FnMut(&mut Self, usize) -> Summary) -> Summary {
        let (start, nodes_before) = (self.out.len(), self.nodes);
        self.out.extend([0, 0]);
        let mut sums = [Summary::Empty; 8];
        for (c, s) in sums.iter_mut().enumerate() {
            *s = child(self, c);
        }
        let first = sums[0];
        if !keep
            && matches!(first, Summary::Free | Summary::Occupied)
            && sums.iter().all(|&s| s == first)
        {
            self.out.truncate(start);
            self.nodes = nodes_before;
            return first;
        }
        if !keep && sums.iter().all(|&s| s == Summary::Empty) {
            self.out.truncate(start);
            return Summary::Empty;
        }
        for (c, s) in sums.iter().enumerate() {
            self.out[start + c / 4] |= s.code() << (2 * (c % 4));
            self.nodes += u64::from(*s != Summary::Empty);
        }
        Summary::Mixed
    }

    /// The part of a leaf with edge `1 << k` voxels at in-leaf corner `base`.
    fn cube(&mut self, leaf: &LeafOccupancy, k: u32, base: [i32; 3]) -> Summary {
        if k == 0 {
            let i = (base[0] | base[1] << 3 | base[2] << 6) as usize;
            return match (leaf.known.get(i), leaf.occupied.get(i)) {
                (false, _) => Summary::Empty,
                (true, false) => Summary::Free,
                (true, true) => Summary::Occupied,
            };
        }
        let h = 1 << (k - 1);
        self.inner(false, |w, c| {
            let c = c as i32;
            let b = [
                base[0] + (c & 1) * h,
                base[1] + (c >> 1 & 1) * h,
                base[2] + (c >> 2 & 1) * h,
            ];
            w.cube(leaf, k - 1, b)
        })
    }

    /// The node at `depth` (< [`LEAF_DEPTH`]) holding `leaves`, sorted by Morton code.
    fn node(&mut self, depth: u32, leaves: &[(u64, LeafOccupancy)]) -> Summary {
        let shift = 3 * (LEAF_DEPTH - 1 - depth);
        let mut rest = leaves;
        self.inner(depth == 0, |w, c| {
            let n = rest.partition_point(|(m, _)| (m >> shift & 7) as usize == c);
            let (here, tail) = rest.split_at(n);
            rest = tail;
            match here {
                [] => Summary::Empty,
                [(_, leaf)] if depth + 1 == LEAF_DEPTH => w.cube(leaf, 3, [0; 3]),
                _ => w.node(depth + 1, here),
            }
        })
    }
}

/// Spread the low 13 bits of `v` to every third bit.
fn spread(v: u64) -> u64 {
    (0..13).fold(0, |acc, b| acc | (v >> b & 1) << (3 * b))
}

fn leaf_key(origin: VoxelCoord) -> Result<u64, BtError> {
    let o = origin.to_array();
    if o.iter().any(|&c| c & 7 != 0) {
        return Err(BtError::Unaligned { origin });
    }
    if o.iter()
        .any(|c| !(-KEY_OFFSET..=KEY_OFFSET - 8).contains(c))
    {
        return Err(BtError::OutOfRange { origin });
    }
    let k = o.map(|c| ((c + KEY_OFFSET) >> 3) as u64);
    Ok(spread(k[0]) | spread(k[1]) << 1 | spread(k[2]) << 2)
}

/// Encode leaves as a `.bt` file at `resolution` metres. Leaves with nothing known are
/// ignored; a leaf outside the key space is an error, not silently dropped.
pub fn encode_bt(
    leaves: impl IntoIterator<Item = LeafOccupancy>,
    resolution: f64,
) -> Result<Vec<u8>, BtError> {
    let (nodes, data) = encode_bt_data(leaves)?;
    let mut file = format!(
        "{HEADER_LINE}\n# (written by voxmap)\n#\nid OcTree\nsize {nodes}\nres {resolution}\ndata\n"
    )
    .into_bytes();
    file.extend_from_slice(&data);
    Ok(file)
}

/// The tree data of a `.bt` file without its text header, and its node count: what
/// OctoMap's `OcTree::writeBinaryData` writes, and what an `octomap_msgs/msg/Octomap`
/// message carries.
pub fn encode_bt_data(
    leaves: impl IntoIterator<Item = LeafOccupancy>,
) -> Result<(u64, Vec<u8>), BtError> {
    let mut keyed = Vec::new();
    for l in leaves {
        if !l.known.is_empty() {
            keyed.push((leaf_key(l.origin)?, l));
        }
    }
    keyed.sort_unstable_by_key(|(m, _)| *m);
    if let Some(w) = keyed.windows(2).find(|w| w[0].0 == w[1].0) {
        return Err(BtError::Duplicate {
            origin: w[0].1.origin,
        });
    }
    let mut w = Writer {
        out: Vec::new(),
        nodes: 0,
    };
    if !keyed.is_empty() {
        w.nodes = 1;
        w.node(0, &keyed);
    }
    Ok((w.nodes, w.out))
}

/// What a `.bt` file holds, voxels counted at full depth (a pruned leaf at depth `d`
/// stands for `8^(16-d)` voxels).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct BtSummary {
    pub resolution: f64,
    /// Nodes, root included, as the `size` line states and the data confirms.
    pub nodes: u64,
    pub occupied_voxels: u64,
    pub free_voxels: u64,
    /// Occupied leaf nodes (a pruned node counts once), as `bt2vrml` counts them.
    pub occupied_leaves: u64,
}

/// Parse the text header: (resolution, stated node count, offset of the tree data).
fn parse_header(bytes: &[u8]) -> Result<(f64, u64, usize), BtError> {
    let bad = |m: &str| BtError::Format(m.to_string());
    let mut pos = 0;
    let mut line = || -> Result<&[u8], BtError> {
        let rest = bytes.get(pos..).unwrap_or(&[]);
        let n = rest
            .iter()
            .take(4096)
            .position(|&b| b == b'\n')
            .ok_or_else(|| bad("header line missing or longer than 4096 bytes"))?;
        pos += n + 1;
        Ok(&rest[..n])
    };
    if line()?.trim_ascii_end() != HEADER_LINE.as_bytes() {
        return Err(bad("first line is not '# Octomap OcTree binary file'"));
    }
    let (mut id, mut size, mut res) = (None, None, None);
    loop {
        let l = std::str::from_utf8(line()?).map_err(|_| bad("header is not text"))?;
        let l = l.trim();
        if l.starts_with('#') || l.is_empty() {
            continue;
        }
        let (k, v) = l.split_once(' ').unwrap_or((l, ""));
        match k {
            "id" => id = Some(v.trim().to_string()),
            "size" => {
                size = Some(
                    v.trim()
                        .parse::<u64>()
                        .map_err(|_| bad("size is not a number"))?,
                )
            }
            "res" => {
                res = Some(
                    v.trim()
                        .parse::<f64>()
                        .map_err(|_| bad("res is not a number"))?,
                )
            }
            "data" => break,
            _ => return Err(BtError::Format(format!("unknown header key '{k}'"))),
        }
    }
    if id.as_deref() != Some("OcTree") {
        return Err(BtError::Format(format!("tree type {id:?} is not OcTree")));
    }
    let size = size.ok_or_else(|| bad("no size line"))?;
    let resolution = res.ok_or_else(|| bad("no res line"))?;
    if !(resolution.is_finite() && resolution > 0.0) {
        return Err(bad("res must be finite and > 0"));
    }
    Ok((resolution, size, pos))
}

/// Read a `.bt` file's header and walk its tree, checking every byte is accounted for.
pub fn read_bt(bytes: &[u8]) -> Result<BtSummary, BtError> {
    let bad = |m: &str| BtError::Format(m.to_string());
    let (resolution, size, pos) = parse_header(bytes)?;
    let mut s = BtSummary {
        resolution,
        ..Default::default()
    };
    let data = &bytes[pos..];
    let mut at = 0;
    if size > 0 {
        s.nodes = 1;
        // Explicit stack of (depth, children left to visit in the current node's list).
        let mut stack: Vec<(u32, [u8; 8], usize)> = Vec::new();
        let read_node = |at: &mut usize| -> Result<[u8; 8], BtError> {
            let b = data
                .get(*at..*at + 2)
                .ok_or_else(|| bad("data ends inside the tree"))?;
            *at += 2;
            Ok(std::array::from_fn(|c| b[c / 4] >> (2 * (c % 4)) & 3))
        };
        stack.push((0, read_node(&mut at)?, 0));
        while let Some(top) = stack.last_mut() {
            let (depth, codes, next) = (top.0, top.1, top.2);
            if next == 8 {
                stack.pop();
                continue;
            }
            top.2 += 1;
            let voxels = 1u64 << (3 * (DEPTH - depth - 1));
            match codes[next] {
                0 => {}
                1 => {
                    s.nodes += 1;
                    s.free_voxels += voxels;
                }
                2 => {
                    s.nodes += 1;
                    s.occupied_leaves += 1;
                    s.occupied_voxels += voxels;
                }
                _ if depth + 1 == DEPTH => {
                    return Err(bad("tree deeper than 16 levels (a voxel with children)"));
                }
                _ => {
                    s.nodes += 1;
                    let child = read_node(&mut at)?;
                    stack.push((depth + 1, child, 0));
                }
            }
        }
    }
    if s.nodes != size {
        return Err(BtError::Format(format!(
            "size line says {size} nodes, the data holds {}",
            s.nodes
        )));
    }
    if at != data.len() {
        return Err(BtError::Format(format!(
            "{} bytes after the tree",
            data.len() - at
        )));
    }
    Ok(s)
}

/// Decode a `.bt` file into leaves (pruned nodes expanded to voxels). Refuses files that
/// would expand to more than `max_voxels` known voxels.
pub fn decode_bt(bytes: &[u8], max_voxels: u64) -> Result<(f64, Vec<LeafOccupancy>), BtError> {
    let s = read_bt(bytes)?;
    if s.occupied_voxels + s.free_voxels > max_voxels {
        return Err(BtError::Format(format!(
            "{} known voxels is more than the limit of {max_voxels}",
            s.occupied_voxels + s.free_voxels
        )));
    }
    let data = &bytes[parse_header(bytes)?.2..];
    let mut leaves: hashbrown::HashMap<[i32; 3], LeafOccupancy> = hashbrown::HashMap::new();
    if s.nodes == 0 {
        return Ok((s.resolution, Vec::new()));
    }
    let mut at = 0usize;
    // (depth, key of the node's min corner, codes, next child)
    let mut stack: Vec<(u32, [i32; 3], [u8; 8], usize)> = Vec::new();
    let codes_at = |at: usize| -> [u8; 8] {
        // In range: read_bt walked this same tree within `data`.
        std::array::from_fn(|c| data.get(at + c / 4).map_or(0, |b| b >> (2 * (c % 4)) & 3))
    };
    stack.push((0, [0; 3], codes_at(0), 0));
    at += 2;
    while let Some(top) = stack.last_mut() {
        let (depth, key, codes, next) = *top;
        if next == 8 {
            stack.pop();
            continue;
        }
        top.3 += 1;
        let half = 1i32 << (DEPTH - depth - 1);
        let c = next as i32;
        let k = [
            key[0] + (c & 1) * half,
            key[1] + (c >> 1 & 1) * half,
            key[2] + (c >> 2 & 1) * half,
        ];
        match codes[next] {
            0 => {}
            3 => {
                stack.push((depth + 1, k, codes_at(at), 0));
                at += 2;
            }
            // A pruned node of whole leaves: set their masks, not voxel by voxel.
            code if half >= 8 => {
                let full = if code == 2 {
                    Mask512::FULL
                } else {
                    Mask512::EMPTY
                };
                for z in (0..half).step_by(8) {
                    for y in (0..half).step_by(8) {
                        for x in (0..half).step_by(8) {
                            let o = [
                                k[0] + x - KEY_OFFSET,
                                k[1] + y - KEY_OFFSET,
                                k[2] + z - KEY_OFFSET,
                            ];
                            leaves.insert(
                                o,
                                LeafOccupancy {
                                    origin: VoxelCoord::from_array(o),
                                    known: Mask512::FULL,
                                    occupied: full,
                                },
                            );
                        }
                    }
                }
            }
            code => {
                let occupied = code == 2;
                for z in 0..half {
                    for y in 0..half {
                        for x in 0..half {
                            let v = [
                                k[0] + x - KEY_OFFSET,
                                k[1] + y - KEY_OFFSET,
                                k[2] + z - KEY_OFFSET,
                            ];
                            let o = v.map(|c| c & !7);
                            let i = ((v[0] & 7) | (v[1] & 7) << 3 | (v[2] & 7) << 6) as usize;
                            let e = leaves.entry(o).or_insert(LeafOccupancy {
                                origin: VoxelCoord::from_array(o),
                                known: Mask512::EMPTY,
                                occupied: Mask512::EMPTY,
                            });
                            e.known.set(i);
                            if occupied {
                                e.occupied.set(i);
                            }
                        }
                    }
                }
            }
        }
    }
    Ok((s.resolution, leaves.into_values().collect()))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::test_rng::Rng;

    fn leaf(origin: [i32; 3], known: &[usize], occupied: &[usize]) -> LeafOccupancy {
        let mut l = LeafOccupancy {
            origin: VoxelCoord::from_array(origin),
            known: Mask512::EMPTY,
            occupied: Mask512::EMPTY,
        };
        for &i in known {
            l.known.set(i);
        }
        for &i in occupied {
            l.known.set(i);
            l.occupied.set(i);
        }
        l
    }

    fn sorted(mut v: Vec<LeafOccupancy>) -> Vec<LeafOccupancy> {
        v.sort_by_key(|l| l.origin.to_array());
        v
    }

    #[test]
    fn single_voxel_tree_has_one_node_per_level() {
        let bt = encode_bt([leaf([0, 0, 0], &[], &[0])], 0.1).unwrap();
        let s = read_bt(&bt).unwrap();
        // Root plus one node per level down to the voxel.
        assert_eq!(s.nodes, 17);
        assert_eq!((s.occupied_voxels, s.free_voxels), (1, 0));
        // 16 inner nodes of 2 bytes.
        let data = &bt[bt.windows(5).position(|w| w == b"data\n").unwrap() + 5..];
        assert_eq!(data.len(), 32);
        // Voxel 0 has key 32768: child 7 (x, y, z bit 15 set) of the root, then child 0.
        assert_eq!(data[0..2], [0, 0b11 << 6]);
        assert_eq!(data[2..4], [0b11, 0]);
        assert_eq!(data[30..32], [0b10, 0]);
    }

    #[test]
    fn full_uniform_leaf_is_pruned_to_one_node() {
        let all: Vec<usize> = (0..512).collect();
        let bt = encode_bt([leaf([-8, 8, 16], &all, &[])], 0.05).unwrap();
        let s = read_bt(&bt).unwrap();
        assert_eq!(s.nodes, 14);
        assert_eq!((s.occupied_voxels, s.free_voxels), (0, 512));
        let half: Vec<usize> = (0..256).collect();
        let bt = encode_bt([leaf([0, 0, 0], &all[256..], &half)], 0.05).unwrap();
        let s = read_bt(&bt).unwrap();
        // Two pruned 8x8x4 sides = 4 pruned 4x4x4 children each under the leaf node.
        assert_eq!(s.nodes, 13 + 1 + 8);
        assert_eq!((s.occupied_voxels, s.free_voxels), (256, 256));
    }

    #[test]
    fn random_leaves_round_trip() {
        let mut rng = Rng(7);
        for round in 0..20 {
            let mut leaves = hashbrown::HashMap::new();
            for _ in 0..1 + round * 3 {
                let o = [0; 3].map(|_| (rng.i(-32, 31)) * 8);
                let mut l = leaf(o, &[], &[]);
                let dense = rng.f() < 0.5;
                for i in 0..512 {
                    if dense || rng.f() < 0.25 {
                        l.known.set(i);
                        if rng.f() < 0.33 {
                            l.occupied.set(i);
                        }
                    }
                }
                leaves.insert(o, l);
            }
            let leaves: Vec<_> = leaves.into_values().collect();
            let bt = encode_bt(leaves.clone(), 0.1).unwrap();
            let (res, back) = decode_bt(&bt, u64::MAX).unwrap();
            assert_eq!(res, 0.1);
            assert_eq!(sorted(back), sorted(leaves.clone()));
            let s = read_bt(&bt).unwrap();
            let occ: u64 = leaves.iter().map(|l| l.occupied.count() as u64).sum();
            let known: u64 = leaves.iter().map(|l| l.known.count() as u64).sum();
            assert_eq!((s.occupied_voxels, s.free_voxels), (occ, known - occ));
        }
    }

    #[test]
    fn key_space_edges() {
        let ok = encode_bt(
            [
                leaf([-32768, -32768, -32768], &[0], &[]),
                leaf([32760; 3], &[], &[511]),
            ],
            1.0,
        )
        .unwrap();
        let (_, back) = decode_bt(&ok, u64::MAX).unwrap();
        assert_eq!(back.len(), 2);
        assert_eq!(
            encode_bt([leaf([32768, 0, 0], &[0], &[])], 1.0),
            Err(BtError::OutOfRange {
                origin: VoxelCoord::new(32768, 0, 0)
            })
        );
        assert!(matches!(
            encode_bt([leaf([4, 0, 0], &[0], &[])], 1.0),
            Err(BtError::Unaligned { .. })
        ));
        assert!(matches!(
            encode_bt([leaf([0; 3], &[0], &[]), leaf([0; 3], &[1], &[])], 1.0),
            Err(BtError::Duplicate { .. })
        ));
    }

    #[test]
    fn empty_map_and_corrupt_files() {
        let bt = encode_bt([], 0.2).unwrap();
        assert_eq!(read_bt(&bt).unwrap().nodes, 0);
        let good = encode_bt([leaf([0, 0, 0], &[1, 2, 3], &[9])], 0.1).unwrap();
        for cut in 0..good.len() {
            assert!(read_bt(&good[..cut]).is_err(), "truncated at {cut}");
        }
        let mut extra = good.clone();
        extra.push(0);
        assert!(read_bt(&extra).is_err());
        let n = read_bt(&good).unwrap().nodes;
        let needle = format!("size {n}\n");
        let at = good
            .windows(needle.len())
            .position(|w| w == needle.as_bytes())
            .unwrap();
        let mut lying = good[..at].to_vec();
        lying.extend(format!("size {}\n", n + 1).bytes());
        lying.extend(&good[at + needle.len()..]);
        assert!(matches!(read_bt(&lying), Err(BtError::Format(m)) if m.contains("says")));
        // A header that stops before its size, resolution and data lines.
        let cut = b"# Octomap OcTree binary file\nid OcTree\n";
        assert!(matches!(read_bt(cut), Err(BtError::Format(m)) if !m.contains("first line")));
    }

    fn bt(size: usize, nodes: &[[u8; 2]]) -> Vec<u8> {
        let mut b =
            format!("# Octomap OcTree binary file\nid OcTree\nsize {size}\nres 0.1\ndata\n")
                .into_bytes();
        nodes.iter().for_each(|n| b.extend(n));
        b
    }

    #[test]
    fn deep_and_pruned_trees() {
        // Inner nodes down to depth 16, where voxels are: refused, not read as voxels.
        let mut deep = vec![[3, 0]; 16];
        deep.push([0, 0]);
        assert!(matches!(read_bt(&bt(17, &deep)), Err(BtError::Format(m)) if m.contains("deeper")));
        // Inner nodes down to depth 12, whose first child is a pruned occupied 8^3 block
        // and second a free one: two whole leaves, and the same file again on encoding.
        let mut pruned = vec![[3, 0]; 12];
        pruned.push([2 | 1 << 2, 0]);
        let file = bt(15, &pruned);
        let (res, mut leaves) = decode_bt(&file, 1 << 20).unwrap();
        leaves.sort_by_key(|l| l.origin);
        let o = -(1 << 15);
        assert_eq!(
            leaves,
            vec![
                LeafOccupancy {
                    origin: VoxelCoord::new(o, o, o),
                    known: Mask512::FULL,
                    occupied: Mask512::FULL
                },
                LeafOccupancy {
                    origin: VoxelCoord::new(o + 8, o, o),
                    known: Mask512::FULL,
                    occupied: Mask512::EMPTY
                },
            ]
        );
        let again = encode_bt(leaves, res).unwrap();
        let data = |b: &[u8]| b[b.windows(5).position(|w| w == b"data\n").unwrap() + 5..].to_vec();
        assert_eq!(data(&again), data(&file));
        assert!(
            decode_bt(&file, 1000).is_err(),
            "1024 voxels over the limit"
        );
    }

    /// A file OctoMap itself wrote reads back, and re-encoding its voxels gives the
    /// same bytes: same tree order, same codes, same pruning.
    #[test]
    fn octomaps_own_file_round_trips_byte_for_byte() {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../../shared/data/real/octomap/geb079.bt");
        let Ok(bytes) = std::fs::read(&path) else {
            panic!(
                "{} is missing: the shared data must sit beside the repo",
                path.display()
            );
        };
        let s = read_bt(&bytes).unwrap();
        // What OctoMap 1.9.7's own tools report for this file: `compare_octrees` reads
        // 532566 nodes and expands 1136432 leaves; `bt2vrml` writes 143729 occupied voxels.
        assert_eq!(s.nodes, 532_566);
        assert_eq!(s.occupied_voxels + s.free_voxels, 1_136_432);
        assert_eq!(s.occupied_leaves, 143_729);
        let (res, leaves) = decode_bt(&bytes, 1 << 28).unwrap();
        let again = encode_bt(leaves, res).unwrap();
        let data = |b: &[u8]| b[b.windows(5).position(|w| w == b"data\n").unwrap() + 5..].to_vec();
        assert_eq!(data(&again), data(&bytes));
        assert_eq!(read_bt(&again).unwrap(), s);
    }
}

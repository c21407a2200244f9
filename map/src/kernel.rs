//! The vector kernels: which one a process runs, and the one table of entry points through
//! which every phase with a vector form calls it.
//!
//! **The rule.** A process runs one kernel, chosen once: the best the CPU has
//! ([`Kernel::detect`]), unless `VOXMAP_KERNEL=scalar|avx2|avx512` names another
//! ([`Kernel::process`]); asking for one the CPU lacks is an error, not a crash. The choice
//! resolves into a [`Kernels`] table of function pointers, one per phase: making rays and
//! noting their cells, the dense and sparse walks, the update's observation of a leaf, the
//! distance field's passes and the snapshot encoder. Every kernel computes exactly what
//! `Scalar` does; tests hold one table per kernel ([`Kernel::table`]) to compare them.
//!
//! This file is the only place that names a kernel's variants: everywhere else a phase
//! calls its entry in the table it was given. The vector functions are `#[target_feature]`
//! functions; the tables are private statics, reachable only through [`Kernel::table`],
//! which refuses a kernel the CPU cannot run. That check is what makes each entry's
//! `unsafe` call sound.

use crate::field::patch::{self, Region, Scratch};
use crate::grid::Leaf;
use crate::integrate::marks::{FrameMarks, Slot};
use crate::integrate::ray::{CellKeys, ChunkOrder, ExtentSum, Ray, RayMaker, Sides};
use crate::integrate::select::{CellBox, Chooser};
use crate::integrate::update;
use crate::integrate::walk::covered::Covered;
use crate::integrate::walk::dense::{self, DenseBits, DenseBox};
use crate::integrate::walk::sparse;
use crate::mask::Mask512;
use crate::model::QuantizedModel;
use crate::snapshot::encode::{self, PlannedLeaf, Sums};
use std::ops::Range;
use std::sync::OnceLock;

#[cfg(target_arch = "x86_64")]
use crate::integrate::walk::{avx2 as walk_avx2, avx512 as walk_avx512};
#[cfg(target_arch = "x86_64")]
use crate::integrate::{ray, select};

/// A set of kernels. Every kernel computes exactly what `Scalar` does.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
#[non_exhaustive]
pub enum Kernel {
    /// Portable Rust, on every CPU.
    Scalar,
    /// AVX2 with FMA, BMI1/2, LZCNT and POPCNT (x86-64-v3: Intel since Haswell, AMD since
    /// Zen): four rays per vector, 32 voxels per update step; the rest compiled for it.
    Avx2,
    /// AVX-512 F, DQ, BW, VL, VBMI2 and VPOPCNTDQ on top of `Avx2`'s features (Intel since
    /// Ice Lake, AMD since Zen 4): eight rays per vector, 64 voxels per update, the
    /// snapshot encoder's compressing stores. A CPU with only the first AVX-512 sets
    /// (Skylake-X) runs `Avx2`.
    Avx512,
}

/// `VOXMAP_KERNEL` names a kernel this build or CPU does not have.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum KernelError {
    /// Not a kernel's name.
    Unknown(String),
    /// A kernel the CPU lacks the instructions for.
    Unsupported(Kernel),
}

impl std::fmt::Display for KernelError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Unknown(s) => write!(
                f,
                "VOXMAP_KERNEL={s:?} is no kernel of this build (scalar, avx2, avx512)"
            ),
            Self::Unsupported(k) => write!(
                f,
                "this CPU lacks the instructions of the {} kernel (VOXMAP_KERNEL)",
                k.name()
            ),
        }
    }
}

impl std::error::Error for KernelError {}

impl Kernel {
    /// Every kernel, slowest first.
    pub const ALL: [Kernel; 3] = [Kernel::Scalar, Kernel::Avx2, Kernel::Avx512];

    /// The name `VOXMAP_KERNEL` and reports use: `scalar`, `avx2`, `avx512`.
    pub fn name(self) -> &'static str {
        match self {
            Self::Scalar => "scalar",
            Self::Avx2 => "avx2",
            Self::Avx512 => "avx512",
        }
    }

    /// Whether this CPU can run the kernel.
    pub fn supported(self) -> bool {
        match self {
            Self::Scalar => true,
            #[cfg(target_arch = "x86_64")]
            Self::Avx2 => {
                use std::arch::is_x86_feature_detected as has;
                has!("avx2")
                    && has!("fma")
                    && has!("bmi1")
                    && has!("bmi2")
                    && has!("lzcnt")
                    && has!("popcnt")
            }
            #[cfg(target_arch = "x86_64")]
            // The AVX-512 kernel runs AVX2 code where AVX-512 does not pay.
            Self::Avx512 => {
                use std::arch::is_x86_feature_detected as has;
                Self::Avx2.supported()
                    && has!("avx512f")
                    && has!("avx512dq")
                    && has!("avx512bw")
                    && has!("avx512vl")
                    && has!("avx512vbmi2")
                    && has!("avx512vpopcntdq")
            }
            #[cfg(not(target_arch = "x86_64"))]
            Self::Avx2 | Self::Avx512 => false,
        }
    }

    /// The fastest kernel this CPU runs.
    pub fn detect() -> Kernel {
        Self::ALL
            .into_iter()
            .rev()
            .find(|k| k.supported())
            .unwrap_or(Kernel::Scalar)
    }

    /// The process's kernel: the one `VOXMAP_KERNEL` names, or [`Kernel::detect`]'s when it
    /// is unset or empty. Read once per process.
    pub fn process() -> Result<Kernel, KernelError> {
        static K: OnceLock<Result<Kernel, KernelError>> = OnceLock::new();
        K.get_or_init(|| match std::env::var("VOXMAP_KERNEL") {
            Ok(s) if !s.is_empty() => s.parse(),
            _ => Ok(Self::detect()),
        })
        .clone()
    }

    /// The kernels this CPU runs, slowest first (the tests run each).
    pub fn available() -> Vec<Kernel> {
        Self::ALL.into_iter().filter(|k| k.supported()).collect()
    }

    /// This kernel's table of entry points, if the CPU runs it.
    pub fn table(self) -> Result<&'static Kernels, KernelError> {
        if !self.supported() {
            return Err(KernelError::Unsupported(self));
        }
        Ok(match self {
            Self::Scalar => &SCALAR,
            #[cfg(target_arch = "x86_64")]
            Self::Avx2 => &AVX2,
            #[cfg(target_arch = "x86_64")]
            Self::Avx512 => &AVX512,
            #[cfg(not(target_arch = "x86_64"))]
            _ => unreachable!("supported() is false off x86-64"),
        })
    }
}

impl std::str::FromStr for Kernel {
    type Err = KernelError;

    /// A kernel by name, if this CPU runs it.
    fn from_str(s: &str) -> Result<Kernel, KernelError> {
        let k = Self::ALL
            .into_iter()
            .find(|k| k.name() == s)
            .ok_or_else(|| KernelError::Unknown(s.into()))?;
        if k.supported() {
            Ok(k)
        } else {
            Err(KernelError::Unsupported(k))
        }
    }
}

/// What a dense walk's rays walk through: the frame's box and origin, and how the walk is
/// to go, decided per stage by the walk's planner (each kernel takes what applies to it).
#[derive(Clone, Copy)]
pub(crate) struct DenseWalk<'a> {
    pub dbox: &'a DenseBox,
    /// The sensor origin, voxel units.
    pub origin: [f64; 3],
    /// The box around the sensor whose voxels the rays skip.
    pub covered: Option<&'a Covered>,
    /// AVX-512: test each mark before writing it.
    #[cfg_attr(not(target_arch = "x86_64"), allow(dead_code))]
    pub test_first: bool,
    /// AVX2: walk the rays in groups of four instead of refilling each lane as its ray
    /// ends.
    #[cfg_attr(not(target_arch = "x86_64"), allow(dead_code))]
    pub grouped: bool,
}

/// One kernel's entry points, one per phase with a vector form. A `None`-returning entry
/// means "this kernel has no such fused form": the caller then takes the separate steps.
pub struct Kernels {
    kernel: Kernel,
    /// `out[i] = maker.make(&pts[i])` for a leading part of `pts`; returns how many it made
    /// (the caller makes the rest one by one).
    pub(crate) make_rays: fn(&RayMaker, &mut [Ray], &[[f32; 3]]) -> usize,
    /// The rays made, laid out by sides and summed in one pass, or `None`.
    pub(crate) make_laid_out: MakeLaidOut,
    /// The extent of `rays` from `origin`.
    pub(crate) extent_of: fn([f64; 3], &[Ray]) -> ExtentSum,
    /// `out[i] = cells.key(&rays[i])` for a leading part; returns how many.
    pub(crate) cell_keys: fn(&CellKeys, &[Ray], &mut [u64]) -> usize,
    /// `out[i] = cells_box.note_of(cells, sides, &rays[i])` for a leading part; returns how
    /// many.
    pub(crate) notes: fn(&CellBox, &CellKeys, &Sides, &[Ray], &mut [u64]) -> usize,
    /// The rays made, summed and noted in one pass, with the noted words of the set asked
    /// for, or `None`.
    pub(crate) make_noted: MakeNoted,
    /// The dense walk of `rays[ranges[..]]` into one thread's bit grids; returns voxels on
    /// the rays and, of those, the ones skipped in the covered box.
    pub(crate) walk_dense: WalkDense,
    /// The sparse walk of a chunk of rays into the frame's leaf tables; returns voxels on
    /// the rays.
    pub(crate) walk_sparse: fn(&FrameMarks, [f64; 3], &[Ray]) -> u64,
    /// One leaf's marks observed into the map's leaf (see `integrate::update::observe_leaf`).
    pub(crate) observe_leaf: fn(&mut Leaf<i8>, &Slot, &QuantizedModel, bool) -> u64,
    /// The distance field's three passes over one patch (see `field::patch::passes`).
    pub(crate) field_passes: fn(&mut Scratch, usize, usize, Region),
    /// The snapshot records of one piece of leaves (see `snapshot::encode::encode_piece`).
    pub(crate) encode_piece: fn(&mut [PlannedLeaf<'_>], &[Mask512]) -> Encoded,
}

/// Made and laid out: how many rays lie in front and behind, where the layout put each,
/// and their extent.
type MakeLaidOut = fn(&RayMaker, &Sides, &[[f32; 3]], &mut [Ray]) -> Option<LaidOut>;
type LaidOut = ([u32; 2], ChunkOrder, ExtentSum);
/// Made, noted and summed: `(how, points, made, notes, set) -> extent`.
type MakeNoted = fn(Chooser<'_>, &[[f32; 3]], &mut [Ray], &mut [u64], &[u64]) -> Option<ExtentSum>;
/// The dense walk of rays in eight ranges, one a lane; returns voxels on the rays and, of
/// those, the ones skipped.
type WalkDense = fn(&mut DenseBits, &[Ray], [Range<usize>; 8], &DenseWalk<'_>) -> (u64, u64);
/// A piece's record bytes, its sums, and how many of its leaves had nothing known.
type Encoded = (Vec<u8>, Sums, usize);

impl Kernels {
    /// The table of the process's kernel ([`Kernel::process`]).
    pub fn process() -> Result<&'static Kernels, KernelError> {
        Kernel::process()?.table()
    }

    /// The process's table, or the scalar one where `VOXMAP_KERNEL` is invalid: for the
    /// code that has no error to report it through (the snapshot encoder, the distance
    /// field); whatever integrates frames reports it ([`Kernels::process`]).
    pub fn process_or_scalar() -> &'static Kernels {
        Self::process().unwrap_or(&SCALAR)
    }

    /// Which kernel this is.
    pub fn kernel(&self) -> Kernel {
        self.kernel
    }
}

impl std::fmt::Debug for Kernels {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "Kernels({})", self.kernel.name())
    }
}

/// Portable Rust.
static SCALAR: Kernels = Kernels {
    kernel: Kernel::Scalar,
    make_rays: |_, _, _| 0,
    make_laid_out: |_, _, _, _| None,
    extent_of: ExtentSum::of_scalar,
    cell_keys: |_, _, _| 0,
    notes: |_, _, _, _, _| 0,
    make_noted: |_, _, _, _, _| None,
    walk_dense: |bits, rays, ranges, how| {
        dense::walk_rays(bits, how.dbox, how.origin, rays, ranges, how.covered)
    },
    walk_sparse: sparse::walk_rays,
    observe_leaf: update::observe_leaf::<update::Scalar>,
    field_passes: patch::passes,
    encode_piece: encode::encode_piece,
};

// SAFETY (every `unsafe` block of the two tables below): the tables are reachable only
// through `Kernel::table`, which returns `AVX2` only where `Kernel::Avx2.supported()` and
// `AVX512` only where `Kernel::Avx512.supported()`: the CPU then has every feature the
// called functions enable (AVX2's table: avx2, fma, bmi1, bmi2, lzcnt, popcnt; AVX-512's:
// those and avx512 f, dq, bw, vl, vbmi2, vpopcntdq). No entry has other preconditions.

/// Four rays at a time; the rest compiled for x86-64-v3.
#[cfg(target_arch = "x86_64")]
static AVX2: Kernels = Kernels {
    kernel: Kernel::Avx2,
    make_rays: |m, out, pts| unsafe { ray::avx2::make_rays(m, out, pts) },
    make_laid_out: |m, sides, pts, out| unsafe { ray::avx2::make_laid_out(m, sides, pts, out) },
    extent_of: |origin, rays| unsafe { ray::avx2::extent_of(origin, rays) },
    cell_keys: |c, rays, out| unsafe { select::avx2::keys(c, rays, out) },
    notes: |b, c, sides, rays, out| unsafe { select::avx2::notes(b, c, sides, rays, out) },
    make_noted: |how, pts, made, notes, set| unsafe {
        select::avx2::make_noted(how, pts, made, notes, set)
    },
    walk_dense: |bits, rays, ranges, how| unsafe {
        let (dbox, origin) = (how.dbox, how.origin);
        walk_avx2::walk_dense(bits, dbox, origin, rays, ranges, how.covered, how.grouped)
    },
    walk_sparse: |marks, origin, rays| {
        marks.with_cache(|c| unsafe { walk_avx2::walk_sparse(c, origin, rays) })
    },
    observe_leaf: |leaf, slot, q, fresh| unsafe {
        update::avx2::observe_leaf(leaf, slot, q, fresh)
    },
    field_passes: |s, n, r, region| unsafe { patch::passes_avx2(s, n, r, region) },
    encode_piece: |piece, keeps| unsafe { encode::encode_piece_avx2(piece, keeps) },
};

/// Eight rays at a time where AVX-512 pays; AVX2's entries elsewhere.
#[cfg(target_arch = "x86_64")]
static AVX512: Kernels = Kernels {
    kernel: Kernel::Avx512,
    make_rays: |m, out, pts| unsafe { ray::avx512::make_rays(m, out, pts) },
    // The fused passes are AVX2's alone: AVX-512 makes its rays eight at a time instead.
    make_laid_out: |_, _, _, _| None,
    extent_of: AVX2.extent_of,
    cell_keys: AVX2.cell_keys,
    notes: AVX2.notes,
    make_noted: |_, _, _, _, _| None,
    walk_dense: |bits, rays, ranges, how| unsafe {
        let (dbox, origin) = (how.dbox, how.origin);
        walk_avx512::walk_dense(
            bits,
            dbox,
            origin,
            rays,
            ranges,
            how.test_first,
            how.covered,
        )
    },
    walk_sparse: |marks, origin, rays| {
        marks.with_cache(|c| unsafe { walk_avx512::walk_sparse(c, origin, rays) })
    },
    observe_leaf: |leaf, slot, q, fresh| unsafe {
        update::avx512::observe_leaf(leaf, slot, q, fresh)
    },
    field_passes: |s, n, r, region| unsafe { patch::passes_avx512(s, n, r, region) },
    encode_piece: |piece, keeps| unsafe { encode::encode_piece_avx512(piece, keeps) },
};

/// Print a test's notice that it skips a kernel, straight to the process's stderr: the
/// test harness captures `eprintln!` and shows it only for failed tests, and a skipped
/// kernel must be seen in every run, not silently absent.
#[cfg(test)]
pub(crate) fn skip_notice(what: std::fmt::Arguments<'_>) {
    use std::io::Write;
    let _ = writeln!(std::io::stderr(), "NOTICE: {what}");
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_parse_and_unsupported_kernels_are_refused() {
        assert_eq!("scalar".parse(), Ok(Kernel::Scalar));
        assert_eq!(
            "avx2048".parse::<Kernel>(),
            Err(KernelError::Unknown("avx2048".into()))
        );
        assert_eq!("avx2".parse::<Kernel>().is_ok(), Kernel::Avx2.supported());
        let avx512 = "avx512".parse::<Kernel>();
        if Kernel::Avx512.supported() {
            assert_eq!(avx512, Ok(Kernel::Avx512));
            assert_eq!(Kernel::detect(), Kernel::Avx512);
        } else {
            assert_eq!(avx512, Err(KernelError::Unsupported(Kernel::Avx512)));
            let best = if Kernel::Avx2.supported() {
                Kernel::Avx2
            } else {
                Kernel::Scalar
            };
            assert_eq!(Kernel::detect(), best);
        }
        assert_eq!(Kernel::available()[0], Kernel::Scalar);
    }

    #[test]
    fn a_table_is_given_only_for_a_kernel_the_cpu_runs() {
        for k in Kernel::ALL {
            match k.table() {
                Ok(t) => {
                    assert!(k.supported());
                    assert_eq!(t.kernel(), k);
                }
                Err(e) => {
                    assert!(!k.supported());
                    assert_eq!(e, KernelError::Unsupported(k));
                }
            }
        }
    }
}

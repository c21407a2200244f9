//! Which vector kernels a process uses, chosen once at run time from what the CPU reports,
//! so that one binary runs on every x86-64 (and aarch64) robot computer.
//!
//! [`Kernel::detect`] picks the best the CPU has; `VOXMAP_KERNEL=scalar|avx2|avx512` forces one
//! ([`Kernel::from_env`]), for tests and benchmarks; asking for one the CPU lacks is an
//! error, not a crash. Code holding a [`Kernel`] other than `Scalar` may call that
//! kernel's `#[target_feature]` functions: the only ways to make one check the CPU.

/// A set of kernels. Every kernel computes exactly what `Scalar` does.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
#[non_exhaustive]
pub enum Kernel {
    /// Portable Rust, on every CPU.
    Scalar,
    /// AVX2 with FMA, BMI1/2, LZCNT and POPCNT (x86-64-v3: Intel since Haswell, AMD since
    /// Zen): four rays per vector, 32 voxels per update step; the rest compiled for it.
    Avx2,
    /// AVX-512 F, DQ and BW (x86-64): eight rays per vector, 64 voxels per update.
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
            Self::Unsupported(k) => {
                write!(
                    f,
                    "this CPU lacks the instructions of the {} kernel",
                    k.name()
                )
            }
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
            // The AVX-512 kernel runs AVX2 code where AVX-512 does not pay (every AVX-512
            // CPU has AVX2).
            Self::Avx512 => {
                Self::Avx2.supported()
                    && std::arch::is_x86_feature_detected!("avx512f")
                    && std::arch::is_x86_feature_detected!("avx512dq")
                    && std::arch::is_x86_feature_detected!("avx512bw")
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

    /// The kernel `VOXMAP_KERNEL` names, or [`Kernel::detect`]'s when it is unset or empty.
    pub fn from_env() -> Result<Kernel, KernelError> {
        match std::env::var("VOXMAP_KERNEL") {
            Ok(s) if !s.is_empty() => s.parse(),
            _ => Ok(Self::detect()),
        }
    }

    /// [`Kernel::from_env`], read once per process, for the code that holds no integrator
    /// (the snapshot encoder); a bad `VOXMAP_KERNEL` gives `Scalar` here (the integrator
    /// reports it as an error).
    pub fn process() -> Kernel {
        static K: std::sync::OnceLock<Kernel> = std::sync::OnceLock::new();
        *K.get_or_init(|| Self::from_env().unwrap_or(Kernel::Scalar))
    }

    /// The kernels this CPU runs, slowest first (the tests run each).
    pub fn available() -> Vec<Kernel> {
        Self::ALL.into_iter().filter(|k| k.supported()).collect()
    }
}

/// Print a test's notice that it skips a kernel, straight to the process's stderr: the
/// test harness captures `eprintln!` and shows it only for failed tests, and a skipped
/// kernel must be seen in every run, not silently absent.
#[cfg(test)]
pub(crate) fn skip_notice(what: std::fmt::Arguments<'_>) {
    use std::io::Write;
    let _ = writeln!(std::io::stderr(), "NOTICE: {what}");
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
}

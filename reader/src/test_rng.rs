//! A tiny deterministic generator for the unit tests (no dependency, same sequence everywhere).

pub struct Rng(pub u64);

impl Rng {
    /// Uniform in [0, 1).
    pub fn f(&mut self) -> f64 {
        self.0 = self
            .0
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (self.0 >> 11) as f64 / (1u64 << 53) as f64
    }

    /// Uniform integer in [lo, hi].
    pub fn i(&mut self, lo: i32, hi: i32) -> i32 {
        lo + (self.f() * (hi - lo + 1) as f64) as i32
    }

    /// Uniform in the ball of radius `r`.
    pub fn ball(&mut self, r: f64) -> [f32; 3] {
        loop {
            let p = [
                self.f() * 2.0 - 1.0,
                self.f() * 2.0 - 1.0,
                self.f() * 2.0 - 1.0,
            ];
            if p.iter().map(|c| c * c).sum::<f64>() <= 1.0 {
                return p.map(|c| (c * r) as f32);
            }
        }
    }
}

//! A tiny, self-contained, seedable PRNG (PCG-XSH-RR 64/32).
//!
//! The filter owns one, seeded by the caller through
//! [`crate::FilterConfig::seed`], so its output is a pure function of the
//! seed and the inputs, independent of any `rand` version.

/// PCG32 generator with a Box-Muller normal sampler.
#[derive(Debug, Clone)]
pub(crate) struct Pcg32 {
    state: u64,
    inc: u64,
    spare_normal: Option<f64>,
}

impl Pcg32 {
    const MUL: u64 = 6_364_136_223_846_793_005;

    pub fn new(seed: u64) -> Self {
        let mut rng = Self { state: 0, inc: (0xda3e_39cb_94b9_5bdb_u64 << 1) | 1, spare_normal: None };
        rng.next_u32();
        rng.state = rng.state.wrapping_add(seed);
        rng.next_u32();
        rng
    }

    pub fn next_u32(&mut self) -> u32 {
        let old = self.state;
        self.state = old.wrapping_mul(Self::MUL).wrapping_add(self.inc);
        let xorshifted = (((old >> 18) ^ old) >> 27) as u32;
        let rot = (old >> 59) as u32;
        xorshifted.rotate_right(rot)
    }

    /// Uniform in [0, 1).
    pub fn uniform(&mut self) -> f64 {
        let hi = u64::from(self.next_u32()) << 21;
        let lo = u64::from(self.next_u32() >> 11);
        ((hi | lo) as f64) * (1.0 / (1u64 << 53) as f64)
    }

    /// Standard normal.
    pub fn normal(&mut self) -> f64 {
        if let Some(v) = self.spare_normal.take() {
            return v;
        }
        // 1 - u is in (0, 1], so the log is finite.
        let u1 = 1.0 - self.uniform();
        let u2 = self.uniform();
        let r = (-2.0 * u1.ln()).sqrt();
        let (s, c) = (std::f64::consts::TAU * u2).sin_cos();
        self.spare_normal = Some(r * s);
        r * c
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn deterministic_and_plausible() {
        let mut a = Pcg32::new(42);
        let mut b = Pcg32::new(42);
        let mut sum = 0.0;
        let mut sum2 = 0.0;
        for _ in 0..10_000 {
            let x = a.normal();
            assert_eq!(x, b.normal());
            sum += x;
            sum2 += x * x;
        }
        assert!((sum / 1e4).abs() < 0.05);
        assert!((sum2 / 1e4 - 1.0).abs() < 0.05);
        let u = Pcg32::new(7).uniform();
        assert!((0.0..1.0).contains(&u));
        assert_ne!(Pcg32::new(1).next_u32(), Pcg32::new(2).next_u32());
    }
}

//! Seeded random streams. Every copter has its own stream, derived from the scene seed and its
//! id, so results never depend on the order other copters are processed in.

use rand::Rng;
use rand_pcg::Pcg32;
use serde::{Deserialize, Serialize};

use crate::math::Real;

/// A PCG32 stream with the few draws the simulation needs.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Rng32(Pcg32);

/// SplitMix64's finaliser: decorrelates nearby inputs.
#[inline]
fn mix64(seed: u64) -> u64 {
    let mut z = seed.wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// Maps 32 random bits to zero-mean, unit-variance triangular noise on `[−√6, √6]`.
#[inline]
fn triangular_of(x: u32) -> Real {
    let s = (x >> 16) as Real + (x & 0xFFFF) as Real - 65535.0;
    s * (6f32.sqrt() / 65536.0)
}

/// Triangular noise ([`Rng32::triangular`]'s) keyed by `key` under `seed`: a draw that keeps
/// no state, so it is the same whenever and wherever it is made (a pass may run before or
/// after another that draws from a copter's stream, or in another shard, and read the same).
#[inline]
pub fn keyed_triangular(seed: u64, key: [u64; 4]) -> Real {
    let z = key.iter().fold(mix64(seed), |z, &k| mix64(z ^ k));
    triangular_of((z >> 32) as u32)
}

impl Rng32 {
    /// The stream of `stream_id` under `seed`.
    pub fn new(seed: u64, stream_id: u64) -> Self {
        // Decorrelate nearby seeds with a SplitMix64 finaliser.
        Rng32(Pcg32::new(mix64(seed), stream_id.wrapping_mul(2).wrapping_add(1)))
    }

    /// Uniform in [0, 1).
    #[inline]
    pub fn uniform(&mut self) -> Real {
        (self.0.next_u32() >> 8) as Real * (1.0 / (1u32 << 24) as Real)
    }

    /// Standard normal (Box–Muller, one of the pair).
    #[inline]
    pub fn normal(&mut self) -> Real {
        let u1 = 1.0 - self.uniform(); // (0, 1]
        let u2 = self.uniform();
        (-2.0 * crate::math::ln(u1)).sqrt() * crate::math::cos(std::f32::consts::TAU * u2)
    }

    /// Zero-mean, unit-variance noise from one 32-bit draw: the sum of two 16-bit uniforms
    /// (triangular on `[−√6, √6]`). For high-rate sensor noise, where a Box–Muller normal per
    /// physics step and axis would cost more than the rest of the copter's step.
    #[inline]
    pub fn triangular(&mut self) -> Real {
        triangular_of(self.0.next_u32())
    }

    /// Poisson with mean `lambda` (Knuth's method; `lambda` here is a few particles).
    #[inline]
    pub fn poisson(&mut self, lambda: Real) -> u32 {
        if lambda <= 0.0 {
            return 0;
        }
        if lambda > 30.0 {
            // Normal approximation for large means.
            return (lambda + lambda.sqrt() * self.normal()).round().max(0.0) as u32;
        }
        let l = (-lambda).exp();
        let mut k = 0;
        let mut p = 1.0;
        loop {
            p *= self.uniform();
            if p <= l {
                return k;
            }
            k += 1;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn normal_has_unit_variance_and_streams_differ() {
        let mut r = Rng32::new(7, 0);
        let n = 20_000;
        let xs: Vec<Real> = (0..n).map(|_| r.normal()).collect();
        let mean = xs.iter().sum::<Real>() / n as Real;
        let var = xs.iter().map(|x| (x - mean).powi(2)).sum::<Real>() / n as Real;
        assert!(mean.abs() < 0.03 && (var - 1.0).abs() < 0.05, "mean {mean} var {var}");
        assert_ne!(Rng32::new(7, 0).uniform(), Rng32::new(7, 1).uniform());
        assert_ne!(Rng32::new(7, 0).uniform(), Rng32::new(8, 0).uniform());
    }

    #[test]
    fn triangular_noise_has_unit_variance() {
        let mut r = Rng32::new(3, 4);
        let n = 40_000;
        let xs: Vec<Real> = (0..n).map(|_| r.triangular()).collect();
        let mean = xs.iter().sum::<Real>() / n as Real;
        let var = xs.iter().map(|x| (x - mean).powi(2)).sum::<Real>() / n as Real;
        assert!(mean.abs() < 0.02 && (var - 1.0).abs() < 0.03, "mean {mean} var {var}");
    }

    #[test]
    fn keyed_noise_has_unit_variance_and_keys_differ() {
        let n = 40_000u64;
        let xs: Vec<Real> = (0..n).map(|k| keyed_triangular(5, [k / 16, k % 16, 3, 1])).collect();
        let mean = xs.iter().sum::<Real>() / n as Real;
        let var = xs.iter().map(|x| (x - mean).powi(2)).sum::<Real>() / n as Real;
        assert!(mean.abs() < 0.02 && (var - 1.0).abs() < 0.03, "mean {mean} var {var}");
        // Neighbouring draws are uncorrelated.
        let lag: Real = xs.windows(2).map(|w| w[0] * w[1]).sum::<Real>() / (n - 1) as Real;
        assert!(lag.abs() < 0.02, "lag-1 correlation {lag}");
        assert_eq!(keyed_triangular(5, [1, 2, 3, 4]), keyed_triangular(5, [1, 2, 3, 4]));
        assert_ne!(keyed_triangular(5, [1, 2, 3, 4]), keyed_triangular(6, [1, 2, 3, 4]));
        assert_ne!(keyed_triangular(5, [1, 2, 3, 4]), keyed_triangular(5, [2, 1, 3, 4]));
    }

    #[test]
    fn poisson_mean_matches() {
        let mut r = Rng32::new(1, 2);
        let n = 20_000;
        let mean = (0..n).map(|_| r.poisson(2.15) as f64).sum::<f64>() / n as f64;
        assert!((mean - 2.15).abs() < 0.05, "{mean}");
    }
}

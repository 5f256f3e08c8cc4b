//! Statistics in constant memory: [`Sample`] (exact count, mean and maximum, a reservoir for
//! the percentiles) and its [`Summary`]. The interpreter's inter-arrival times and the loop's
//! input latencies are kept in them.

/// A stream of values in constant memory: the exact count, mean and maximum, and a uniform
/// random sample of [`Sample::CAPACITY`] values for the percentiles (reservoir sampling,
/// Vitter's algorithm R, on a fixed-seed generator: the same stream gives the same sample).
/// Statistics of a flood or of a day-long run cost the same few kilobytes.
#[derive(Clone, Debug, Default)]
pub struct Sample {
    values: Vec<f32>,
    seen: u64,
    sum: f64,
    max: f32,
    rng: u64,
}

impl Sample {
    /// Values kept for the percentiles.
    pub const CAPACITY: usize = 4096;

    /// Adds a value (non-finite ones are ignored).
    pub fn push(&mut self, v: f32) {
        if !v.is_finite() {
            return;
        }
        if self.seen == 0 {
            self.values.reserve_exact(Self::CAPACITY);
            self.max = v;
        }
        self.seen += 1;
        self.sum += f64::from(v);
        self.max = self.max.max(v);
        if self.values.len() < Self::CAPACITY {
            self.values.push(v);
        } else {
            // xorshift64*: a cheap, fixed-seed stream.
            self.rng = if self.rng == 0 { 0x9E37_79B9_7F4A_7C15 } else { self.rng };
            self.rng ^= self.rng >> 12;
            self.rng ^= self.rng << 25;
            self.rng ^= self.rng >> 27;
            let j = self.rng.wrapping_mul(0x2545_F491_4F6C_DD1D) % self.seen;
            if let Some(slot) = self.values.get_mut(j as usize) {
                *slot = v;
            }
        }
    }

    /// Count, exact mean and maximum; median and 99th percentile of the sample.
    pub fn summary(&self) -> Summary {
        if self.seen == 0 {
            return Summary::default();
        }
        let mut s = Summary::of(&self.values);
        (s.n, s.mean, s.max) = (self.seen as usize, self.sum / self.seen as f64, f64::from(self.max));
        s
    }
}

/// Order statistics of a sample.
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize)]
pub struct Summary {
    /// Number of values.
    pub n: usize,
    /// Mean.
    pub mean: f64,
    /// Median.
    pub p50: f64,
    /// 99th percentile.
    pub p99: f64,
    /// Maximum.
    pub max: f64,
}

impl Summary {
    /// Summarises `values` (NaNs ignored).
    pub fn of(values: &[f32]) -> Self {
        let mut v: Vec<f64> = values.iter().map(|&x| f64::from(x)).filter(|x| x.is_finite()).collect();
        if v.is_empty() {
            return Self::default();
        }
        v.sort_by(f64::total_cmp);
        let q = |p: f64| v[((v.len() - 1) as f64 * p).round() as usize];
        Self {
            n: v.len(),
            mean: v.iter().sum::<f64>() / v.len() as f64,
            p50: q(0.5),
            p99: q(0.99),
            max: v[v.len() - 1],
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_sample_keeps_exact_count_mean_max_and_fair_percentiles_in_constant_memory() {
        let mut s = Sample::default();
        for k in 0..1_000_000u32 {
            s.push((k % 1000) as f32);
        }
        s.push(f32::NAN);
        let sum = s.summary();
        assert_eq!(sum.n, 1_000_000);
        assert!((sum.mean - 499.5).abs() < 1e-6, "{}", sum.mean);
        assert_eq!(sum.max, 999.0);
        // A uniform sample of 4,096: the median within a few percent of 500.
        assert!((sum.p50 - 500.0).abs() < 30.0, "{}", sum.p50);
        assert!(sum.p99 > 960.0, "{}", sum.p99);
        assert!(s.values.capacity() <= Sample::CAPACITY);
        assert_eq!(Sample::default().summary(), Summary::default());
    }
}

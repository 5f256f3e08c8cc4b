//! The timing of a real copter's telemetry link: when each periodic telemetry message reaches
//! the ground station. The stand-in (`twinswarm copter`) and the twin-synchronisation
//! evaluation draw their messages' times from here.
//!
//! **The measured link** follows the original system's measurement (paper, §VI and Fig. 5;
//! report Fig. 4.2 and 4.3): a message configured every 22 ms reached the ground on average
//! every 27 ms; "some messages are lost, this can be observed through the peaks", a few gaps
//! went beyond 60 ms, some messages came closer together than 22 ms (the firmware's and the
//! radio's buffering), and with two copters flying "the average value is slightly increased".
//! Modelled as: the message's slots are its period apart; each slot is skipped with the
//! probability `q` that makes the mean gap the measured one (`q = 1 − 22/27` for one copter,
//! 2 ms more per further copter sharing the radio channel, the same `q` for every message), so
//! one skip gives a 44 ms gap and two give 66 ms (q² ≈ 3 % of gaps); a delivered message is
//! late by a uniform 0–6 ms, so consecutive gaps range from 16 to 28 ms. The paper gives no
//! histogram; the 6 ms and the 2 ms per copter are chosen to match its words, not fitted.
//!
//! **A saturated link** is what a real log shows when the telemetry mode asks more than the
//! modem carries. The 16 Dec 2015 flight's `vrep` mode asked 4,875 B/s of a 38,400-baud modem
//! (3,840 B/s, 127 %); `FINKEN_SENSOR_MODEL`, configured every 22 ms, arrived with a median
//! gap of 28 ms, mean 35, p95 63, p99 91, 14 % over 50 ms (`scripts/real_flights.py`,
//! docs/real-flights.md). [`LinkTiming::Saturated`] stretches the slots by the load (the link
//! sends no faster than it can), keeps the paper's skips, and spreads each message over a
//! 12 ms window (the modem's queue): fitted to that histogram by least squares over slot,
//! spread and skip, it gives 29 / 34 / 62 / 89 ms and 16 % over 50 ms
//! (`cargo test -p bridge --lib link -- --nocapture`).

use serde::Serialize;
use sim_core::rng::Rng32;

/// The configured period of the paper's measured message, s.
pub const MEASURED_PERIOD_S: f64 = 0.022;
/// Its measured mean gap with one copter flying, s.
pub const MEASURED_MEAN_GAP_S: f64 = 0.027;
/// How much longer the mean gap gets per further copter on the channel, s.
pub const MEASURED_GAP_PER_COPTER_S: f64 = 0.002;
/// A delivered message is late by up to this, uniformly, s.
pub const MEASURED_JITTER_S: f64 = 0.006;
/// On a saturated link, a delivered message is late by up to this, uniformly, s (fitted to the
/// 16 Dec 2015 flight).
pub const SATURATED_JITTER_S: f64 = 0.012;
/// The 16 Dec 2015 flight's load: its telemetry mode's bytes per second over its modem's.
pub const FLIGHT_2015_LOAD: f64 = 4875.0 / 3840.0;

/// How a telemetry link times messages.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum LinkTiming {
    /// Every slot delivered, late by a uniform delay up to `jitter_s`.
    Uniform {
        /// The largest delay, s.
        jitter_s: f64,
    },
    /// The paper's measured link, with `copters` copters sharing the radio channel.
    Measured {
        /// Copters on the channel (at least 1).
        copters: u32,
    },
    /// The measured link asked `load` times what it carries (> 1): slots `load` times further
    /// apart, the paper's skips, [`SATURATED_JITTER_S`].
    Saturated {
        /// Copters on the channel (at least 1).
        copters: u32,
        /// The telemetry mode's bytes per second over the modem's.
        load: f64,
    },
}

impl LinkTiming {
    /// The command line's choice: a uniform link with `jitter_ms` if given, else the measured
    /// link with `copters` on the channel.
    pub fn from_args(jitter_ms: Option<f64>, copters: u32) -> Self {
        match jitter_ms {
            Some(ms) => LinkTiming::Uniform { jitter_s: ms / 1e3 },
            None => LinkTiming::Measured { copters },
        }
    }

    /// The measured link, saturated when `load` (bytes asked over bytes carried) exceeds 1.
    pub fn measured_with_load(copters: u32, load: f64) -> Self {
        if load.is_finite() && load > 1.0 {
            LinkTiming::Saturated { copters, load }
        } else {
            LinkTiming::Measured { copters }
        }
    }

    /// How much further apart than configured the slots are.
    pub fn stretch(self) -> f64 {
        match self {
            LinkTiming::Saturated { load, .. } => load.max(1.0),
            _ => 1.0,
        }
    }

    /// The probability that a slot is skipped.
    pub fn skip_probability(self) -> f64 {
        match self {
            LinkTiming::Uniform { .. } => 0.0,
            LinkTiming::Measured { copters } | LinkTiming::Saturated { copters, .. } => {
                let gap = MEASURED_MEAN_GAP_S + MEASURED_GAP_PER_COPTER_S * f64::from(copters.max(1) - 1);
                1.0 - MEASURED_PERIOD_S / gap
            }
        }
    }

    fn jitter_s(self) -> f64 {
        match self {
            LinkTiming::Uniform { jitter_s } => jitter_s,
            LinkTiming::Measured { .. } => MEASURED_JITTER_S,
            LinkTiming::Saturated { .. } => SATURATED_JITTER_S,
        }
    }
}

/// The send times of one periodic message.
#[derive(Clone, Debug)]
pub struct LinkClock {
    period_s: f64,
    slot: u64,
    skip: f64,
    jitter_s: f64,
    rng: Rng32,
}

impl LinkClock {
    /// A message every `period_s` on a link timed by `timing`, drawing from `rng`.
    pub fn new(period_s: f64, timing: LinkTiming, rng: Rng32) -> Self {
        let period_s = period_s * timing.stretch();
        Self { period_s, slot: 0, skip: timing.skip_probability(), jitter_s: timing.jitter_s(), rng }
    }

    /// When the next message arrives, s after the clock's start (never before the last one's
    /// slot).
    pub fn next_s(&mut self) -> f64 {
        loop {
            self.slot += 1;
            if f64::from(self.rng.uniform()) >= self.skip {
                break;
            }
        }
        self.slot as f64 * self.period_s + self.jitter_s * f64::from(self.rng.uniform())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn gaps(timing: LinkTiming, n: usize) -> Vec<f64> {
        let mut clock = LinkClock::new(MEASURED_PERIOD_S, timing, Rng32::new(7, 1));
        let times: Vec<f64> = (0..n).map(|_| clock.next_s()).collect();
        times.windows(2).map(|w| w[1] - w[0]).collect()
    }

    #[test]
    fn the_measured_link_has_the_papers_mean_gap_tail_and_early_messages() {
        let g = gaps(LinkTiming::Measured { copters: 1 }, 100_000);
        let mean = g.iter().sum::<f64>() / g.len() as f64;
        let share = |f: &dyn Fn(f64) -> bool| g.iter().filter(|&&x| f(x)).count() as f64 / g.len() as f64;
        let (early, over_60) = (share(&|x| x < MEASURED_PERIOD_S), share(&|x| x > 0.060));
        assert!((mean - 0.027).abs() < 0.0003, "mean gap {mean}");
        assert!(early > 0.2, "some closer than the configured 22 ms: {early}");
        assert!((0.005..0.06).contains(&over_60), "a few beyond 60 ms: {over_60}");
        let two = gaps(LinkTiming::Measured { copters: 2 }, 100_000);
        let mean2 = two.iter().sum::<f64>() / two.len() as f64;
        assert!(mean2 > mean + 0.001, "slower with two copters: {mean2} vs {mean}");
    }

    fn percentile(v: &[f64], p: f64) -> f64 {
        let mut s = v.to_vec();
        s.sort_by(f64::total_cmp);
        s[((s.len() - 1) as f64 * p).round() as usize]
    }

    #[test]
    fn the_saturated_link_has_the_2015_flights_gaps() {
        // Real (scripts/real_flights.py on 15_12_16__13_55_00): median 28, mean 35.0, p95 63,
        // p99 91 ms, 14.3 % over 50 ms.
        let g = gaps(LinkTiming::Saturated { copters: 1, load: FLIGHT_2015_LOAD }, 100_000);
        let ms = |x: f64| x * 1e3;
        let mean = ms(g.iter().sum::<f64>() / g.len() as f64);
        let over_50 = g.iter().filter(|&&x| x > 0.050).count() as f64 / g.len() as f64;
        let [p50, p95, p99] = [0.5, 0.95, 0.99].map(|p| ms(percentile(&g, p)));
        println!(
            "saturated link, load {FLIGHT_2015_LOAD:.2}: median {p50:.1} ms, mean {mean:.1}, p95 {p95:.1}, p99 {p99:.1}, over 50 ms {:.1} %",
            over_50 * 100.0
        );
        assert!((26.0..32.0).contains(&p50) && (32.0..38.0).contains(&mean), "{p50} {mean}");
        assert!((58.0..68.0).contains(&p95) && (84.0..98.0).contains(&p99), "{p95} {p99}");
        assert!((0.11..0.18).contains(&over_50), "{over_50}");
        // Not saturated: the paper's link.
        assert_eq!(LinkTiming::measured_with_load(1, 0.9), LinkTiming::Measured { copters: 1 });
    }

    #[test]
    fn the_uniform_link_delivers_every_slot() {
        let g = gaps(LinkTiming::Uniform { jitter_s: 0.01 }, 10_000);
        let mean = g.iter().sum::<f64>() / g.len() as f64;
        assert!((mean - MEASURED_PERIOD_S).abs() < 1e-5, "{mean}");
        assert!(g.iter().all(|&x| x > MEASURED_PERIOD_S - 0.0101 && x < MEASURED_PERIOD_S + 0.0101));
    }
}

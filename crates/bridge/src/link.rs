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

    /// The probability that a slot is skipped.
    pub fn skip_probability(self) -> f64 {
        match self {
            LinkTiming::Uniform { .. } => 0.0,
            LinkTiming::Measured { copters } => {
                let gap = MEASURED_MEAN_GAP_S + MEASURED_GAP_PER_COPTER_S * f64::from(copters.max(1) - 1);
                1.0 - MEASURED_PERIOD_S / gap
            }
        }
    }

    fn jitter_s(self) -> f64 {
        match self {
            LinkTiming::Uniform { jitter_s } => jitter_s,
            LinkTiming::Measured { .. } => MEASURED_JITTER_S,
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

    #[test]
    fn the_uniform_link_delivers_every_slot() {
        let g = gaps(LinkTiming::Uniform { jitter_s: 0.01 }, 10_000);
        let mean = g.iter().sum::<f64>() / g.len() as f64;
        assert!((mean - MEASURED_PERIOD_S).abs() < 1e-5, "{mean}");
        assert!(g.iter().all(|&x| x > MEASURED_PERIOD_S - 0.0101 && x < MEASURED_PERIOD_S + 0.0101));
    }
}

//! The FINken's own height loop, as the lab flew it on 16 Dec 2015
//! (`finken_model_system.c` and `finken_model_actuators.c` of
//! `../shared/paparazzi/finken_firmware/flight_2015-12`, aircraft 5's `5_param.xml`):
//!
//! - every `1 / rate_hz` s (the module's `FINKEN_SYSTEM_UPDATE_FREQ`, 30 Hz) the error between
//!   the set point and the **raw IR reading** (`finken_sensor_model.pos.z`: the slant range,
//!   no filter, no tilt correction) goes through a discrete PIDT1 (Tustin, gain `Kp`, follow
//!   time `Tn`, hold time `Tv`, delay `T1`);
//! - its output, in percent, is added to `THRUST_DEFAULT`; outside [0.25, 1] the firmware takes
//!   back twice the last three errors' share (its anti-windup) and clamps;
//! - that set point is the motor command: the flight plan of that day flies it
//!   (`throttle="finken_actuators_set_point.thrust"`, `free_flight.xml`). The module's
//!   `compensate_battery_drop` (`+ (THRUST_LOW − THRUST_DEFAULT)·(84 − vsupply)/19`, `vsupply`
//!   in whole decivolts, clamped to [0.2, 1]) computes `finken_actuators_model.thrust`, which
//!   that plan logs but does not fly; `battery_compensation` flies it instead.
//!
//! The firmware does no tilt compensation and no thrust adaptation. The motor command becomes
//! the rotors' wanted thrust in proportion to `hover_command`, the command that hovers the
//! copter at the battery's calibration voltage (the ESCs then turn the rotors slower as the
//! pack sags, `battery.rs`).

use serde::{Deserialize, Serialize};

use crate::math::Real;

/// The lab firmware's height loop parameters: `[airframes.NAME.finken_height]` in a scene.
/// Present, it replaces the newton PID (`height_kp_n_per_m` …) while a height is held.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct FinkenHeightSpec {
    /// `FINKEN_SYSTEM_UPDATE_FREQ`: how often the loop runs, Hz.
    pub rate_hz: Real,
    /// `FINKEN_HEIGHT_CONTROL_GAIN` `Kp`: thrust set point, percent, per m of error.
    pub gain_percent_per_m: Real,
    /// `FINKEN_HEIGHT_CONTROL_FOLLOW_TIME` `Tn` (integral time), s.
    pub follow_time_s: Real,
    /// `FINKEN_HEIGHT_CONTROL_HOLD_TIME` `Tv` (derivative time), s.
    pub hold_time_s: Real,
    /// `FINKEN_HEIGHT_CONTROL_DELAY_TIME` `T1` (the derivative's lag), s.
    pub delay_time_s: Real,
    /// `FINKEN_THRUST_DEFAULT`: the set point with no error.
    pub thrust_default: Real,
    /// `FINKEN_THRUST_LOW`: the battery compensation's span (against `thrust_default`).
    pub thrust_low: Real,
    /// Whether the motors get `compensate_battery_drop`'s command rather than the set point
    /// (false: as flown on 16 Dec 2015).
    pub battery_compensation: bool,
    /// The motor command that hovers the copter at the battery's calibration voltage. 0.429:
    /// the real FINken's hover set point, 1.0765 − 0.0583 V (both battery flights,
    /// docs/real-flights.md §5), at the 11.1 V calibration; 16 Dec 2015's flights flew
    /// 0.36-0.41 (`ROTORCRAFT_FP.thrust`).
    pub hover_command: Real,
}

impl Default for FinkenHeightSpec {
    /// Aircraft 5 on 16 Dec 2015 ("Hoehenregler 1").
    fn default() -> Self {
        Self {
            rate_hz: 30.0,
            gain_percent_per_m: 4.741,
            follow_time_s: 6.0,
            hold_time_s: 2.186,
            delay_time_s: 0.0556,
            thrust_default: 0.35,
            thrust_low: 0.40,
            battery_compensation: false,
            hover_command: 0.429,
        }
    }
}

impl FinkenHeightSpec {
    /// The first field out of range, with why.
    pub(crate) fn validate(&self) -> Result<(), (&'static str, String)> {
        let positive = [
            ("finken_height.rate_hz", self.rate_hz),
            ("finken_height.gain_percent_per_m", self.gain_percent_per_m),
            ("finken_height.follow_time_s", self.follow_time_s),
            ("finken_height.delay_time_s", self.delay_time_s),
            ("finken_height.hover_command", self.hover_command),
        ];
        for (field, v) in positive {
            if !(v.is_finite() && v > 0.0) {
                return Err((field, format!("must be finite and positive, got {v}")));
            }
        }
        let unit = [
            ("finken_height.hold_time_s", self.hold_time_s, Real::INFINITY),
            ("finken_height.thrust_default", self.thrust_default, 1.0),
            ("finken_height.thrust_low", self.thrust_low, 1.0),
        ];
        for (field, v, max) in unit {
            if !(v.is_finite() && (0.0..=max).contains(&v)) {
                return Err((field, format!("must be finite, from 0 to {max}, got {v}")));
            }
        }
        if self.hover_command > 1.0 {
            return Err((
                "finken_height.hover_command",
                format!("must be at most 1 (full command), got {}", self.hover_command),
            ));
        }
        Ok(())
    }

    /// The difference equation's coefficients `[a0, a1, b0, b1, b2]`, as the firmware's macros
    /// compute them (`T = 1 / rate_hz`).
    fn coefficients(&self) -> [Real; 5] {
        let (t, t1, tn, tv, kp) =
            (1.0 / self.rate_hz, self.delay_time_s, self.follow_time_s, self.hold_time_s, self.gain_percent_per_m);
        let a0 = (2.0 * t1 - t) / (2.0 * t1 + t);
        let a1 = (-4.0 * t1) / (2.0 * t1 + t);
        let b0 = (t * t - 2.0 * tn * t - 2.0 * tv * t + 4.0 * tn * tv) / (2.0 * tn * t + 4.0 * t1 * tn) * kp;
        let b1 = (t * t - 4.0 * tn * tv) / (tn * t + 2.0 * t1 * tn) * kp;
        let b2 = (t * t + 2.0 * tn * t + 2.0 * tv * t + 4.0 * tn * tv) / (2.0 * tn * t + 4.0 * t1 * tn) * kp;
        [a0, a1, b0, b1, b2]
    }
}

/// The loop's memory: the firmware's `thrust_k_dec1/2` and `error_z_k_dec1/2`, when it runs
/// next, and the motor command it holds until then.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct FinkenHeightState {
    /// Outputs one and two updates back, percent.
    pub output: [Real; 2],
    /// Errors one and two updates back, m.
    pub error: [Real; 2],
    /// Time to the next update, s (0 or less: now).
    pub next_s: Real,
    /// The motor command since the last update, in [0.2, 1] (0 before the first).
    pub command: Real,
}

impl FinkenHeightState {
    /// One physics step of `dt`: runs the loop when it is due, on the IR reading `ir_m`, with
    /// the pack at `battery_v`; returns the motor command held for this step.
    pub fn step(&mut self, spec: &FinkenHeightSpec, setpoint_m: Real, ir_m: Real, battery_v: Real, dt: Real) -> Real {
        if self.next_s <= 0.0 {
            let set_point = self.update(spec, setpoint_m - ir_m);
            self.command =
                if spec.battery_compensation { compensate_battery_drop(spec, set_point, battery_v) } else { set_point };
            self.next_s += 1.0 / spec.rate_hz;
        }
        self.next_s -= dt;
        self.command
    }

    /// `finken_system_model_periodic`'s height part: the thrust set point for error `e`, m.
    fn update(&mut self, spec: &FinkenHeightSpec, e: Real) -> Real {
        let [a0, a1, b0, b1, b2] = spec.coefficients();
        let [u1, u2] = self.output;
        let [e1, e2] = self.error;
        let mut u = -a1 * u1 - a0 * u2 + b2 * e + b1 * e1 + b0 * e2;
        self.error = [e, e1];
        self.output = [u, u1];
        let out_of_range = |u: Real| {
            let s = spec.thrust_default + u / 100.0;
            !(0.25..=1.0).contains(&s)
        };
        if out_of_range(u) {
            // As written: the shifted errors, so `e` counts twice and `e2` not at all.
            let [e1, e2] = self.error;
            u -= 2.0 * (b2 + b1 + b0) * (e + e1 + e2) / 3.0;
        }
        (spec.thrust_default + u / 100.0).clamp(0.25, 1.0)
    }
}

/// `compensate_battery_drop`: the set point plus the compensation for a pack at `battery_v`
/// (read as whole decivolts, `electrical.vsupply`), clamped to [0.2, 1].
pub fn compensate_battery_drop(spec: &FinkenHeightSpec, set_point: Real, battery_v: Real) -> Real {
    let vsupply = (battery_v * 10.0).floor();
    let thrust = set_point + (spec.thrust_low - spec.thrust_default) * (84.0 - vsupply) / (84.0 - 65.0);
    thrust.clamp(0.2, 1.0)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn coefficients_are_the_firmwares() {
        // The firmware's macros evaluated by hand for aircraft 5 (T = 1/30 s).
        let [a0, a1, b0, b1, b2] = FinkenHeightSpec::default().coefficients();
        assert!((a0 - 0.5387).abs() < 1e-3, "{a0}");
        assert!((a1 + 1.5387).abs() < 1e-3, "{a1}");
        assert!((b2 - 144.9).abs() < 0.2, "{b2}");
        // One pole is the integrator's (1 + a1 + a0 = 0); the other is the lag's, at a0.
        assert!((1.0 + a1 + a0).abs() < 1e-6);
        assert!(b0.is_finite() && b1 < 0.0);
    }

    #[test]
    fn a_steady_error_ramps_the_set_point_at_kp_over_tn() {
        let spec = FinkenHeightSpec::default();
        let mut s = FinkenHeightState::default();
        let dt = 1.0 / spec.rate_hz;
        let mut last = 0.0;
        for k in 0..300 {
            last = s.update(&spec, 0.01);
            if k == 150 {
                let slope_per_s = (s.update(&spec, 0.01) - last) / dt * 100.0;
                // Kp / Tn percent per second per metre of error: 4.741 / 6 × 0.01 m.
                assert!((slope_per_s - 4.741 / 6.0 * 0.01).abs() < 2e-3, "{slope_per_s}");
            }
        }
        assert!(last > spec.thrust_default);
    }

    #[test]
    fn battery_compensation_subtracts_on_a_3s_pack_and_clamps() {
        let spec = FinkenHeightSpec::default();
        // 11.9 V: (84 − 119) / 19 × 0.05 = −0.0921.
        assert!((compensate_battery_drop(&spec, 0.4, 11.95) - (0.4 - 0.05 * 35.0 / 19.0)).abs() < 1e-6);
        assert_eq!(compensate_battery_drop(&spec, 0.1, 12.0), 0.2);
        assert_eq!(compensate_battery_drop(&spec, 1.5, 7.0), 1.0);
    }

    #[test]
    fn the_loop_runs_at_its_own_rate_and_holds_between() {
        let spec = FinkenHeightSpec::default();
        let mut s = FinkenHeightState::default();
        let mut changes = 0;
        let mut last = -1.0;
        for k in 0..200 {
            // 1 s of 5 ms steps, a slowly changing error.
            let c = s.step(&spec, 0.6, 0.5 + 0.0005 * k as Real, 11.1, 0.005);
            if c != last {
                changes += 1;
                last = c;
            }
        }
        assert!((29..=31).contains(&changes), "{changes} updates in 1 s");
    }
}

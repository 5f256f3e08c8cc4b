//! The flight battery: a LiPo pack whose voltage falls with its charge and sags under load.
//!
//! The FINken flies on a 3-cell 900 mAh LiPo for about 10 minutes (`paper.txt` §III), and its
//! ESCs do not compensate the pack voltage: the same motor command turns the rotors slower as
//! the pack empties (`report.txt` §3.1.2–3.1.3, §4.1). The model:
//! - open-circuit voltage per cell from the state of charge, piecewise linear through
//!   [`OCV_PER_CELL_V`];
//! - a series internal resistance: `V = E − I R`, with the current from the electrical power,
//!   `I = P / V`, solved exactly (`V = (E + √(E² − 4 P R)) / 2`);
//! - electrical power from the rotors' ideal induced power `T^{3/2} / √(2 ρ A)` divided by an
//!   overall efficiency (figure of merit × motor and ESC efficiency);
//! - the ESC's duty is what the controller asks for at the calibration voltage, so a rotor's
//!   speed scales with `V / V_cal` and its thrust with `(V / V_cal)²`, saturation included.
//!
//! Sources and values: `docs/model.md`.

use serde::{Deserialize, Serialize};

use crate::math::Real;

/// LiPo open-circuit voltage per cell at state of charge 0, 0.05, …, 1 (steps of 5 %), V.
/// A typical resting-voltage table of LiPo cells (see `docs/model.md`).
pub const OCV_PER_CELL_V: [Real; 21] = [
    3.27, 3.61, 3.69, 3.71, 3.73, 3.75, 3.77, 3.79, 3.80, 3.82, 3.84, 3.85, 3.87, 3.91, 3.95, 3.98, 4.02, 4.08, 4.11,
    4.15, 4.20,
];

/// `[airframes.<name>.battery]`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct BatterySpec {
    /// Whether the pack voltage affects the rotors (off: an ideal supply at the calibration
    /// voltage; charge and voltage are still tracked).
    pub enabled: bool,
    /// Cells in series.
    pub cells: u32,
    /// Capacity, mAh.
    pub capacity_mah: Real,
    /// State of charge at the start, in [0, 1].
    pub initial_charge: Real,
    /// Internal resistance of the pack, Ω.
    pub internal_resistance_ohm: Real,
    /// Rotor induced power over electrical power: figure of merit × motor and ESC efficiency.
    pub efficiency: Real,
    /// Pack voltage at which motor commands give the nominal rotor speed, V.
    pub calibration_voltage_v: Real,
}

impl Default for BatterySpec {
    fn default() -> Self {
        Self {
            enabled: true,
            cells: 3,
            capacity_mah: 900.0,
            initial_charge: 1.0,
            internal_resistance_ohm: 0.06,
            efficiency: 0.38,
            calibration_voltage_v: 11.1,
        }
    }
}

impl BatterySpec {
    /// Checks the fields; returns the offending field and why.
    pub fn validate(&self) -> Result<(), (&'static str, String)> {
        if self.cells == 0 || self.cells > 12 {
            return Err(("battery.cells", format!("must be 1 to 12, got {}", self.cells)));
        }
        for (field, v) in [
            ("battery.capacity_mah", self.capacity_mah),
            ("battery.efficiency", self.efficiency),
            ("battery.calibration_voltage_v", self.calibration_voltage_v),
        ] {
            if !v.is_finite() || v <= 0.0 {
                return Err((field, format!("must be positive and finite, got {v}")));
            }
        }
        if self.efficiency > 1.0 {
            return Err(("battery.efficiency", format!("must be at most 1, got {}", self.efficiency)));
        }
        if !self.internal_resistance_ohm.is_finite() || self.internal_resistance_ohm < 0.0 {
            return Err((
                "battery.internal_resistance_ohm",
                format!("must be finite and not negative, got {}", self.internal_resistance_ohm),
            ));
        }
        if !(0.0..=1.0).contains(&self.initial_charge) {
            return Err(("battery.initial_charge", format!("must be in [0, 1], got {}", self.initial_charge)));
        }
        Ok(())
    }

    /// Open-circuit voltage of the pack at a state of charge, V.
    #[inline]
    pub fn open_circuit_v(&self, charge: Real) -> Real {
        let x = charge.clamp(0.0, 1.0) * 20.0;
        let i = (x as usize).min(19);
        let f = x - i as Real;
        self.cells as Real * (OCV_PER_CELL_V[i] + f * (OCV_PER_CELL_V[i + 1] - OCV_PER_CELL_V[i]))
    }
}

/// A pack's state.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct BatteryState {
    /// State of charge, in [0, 1].
    pub charge: Real,
    /// Terminal voltage under the last load, V.
    pub voltage_v: Real,
    /// Current drawn in the last physics step, A.
    pub current_a: Real,
}

impl BatteryState {
    /// A pack at its initial charge, unloaded.
    pub fn new(spec: &BatterySpec) -> Self {
        Self { charge: spec.initial_charge, voltage_v: spec.open_circuit_v(spec.initial_charge), current_a: 0.0 }
    }

    /// Draws `power_w` for `dt` seconds: updates the terminal voltage, current and charge.
    /// A load the pack cannot deliver (`E² < 4 P R`) gets the voltage at maximum power, `E / 2`.
    #[inline]
    pub fn draw(&mut self, spec: &BatterySpec, power_w: Real, dt: Real) {
        let e = spec.open_circuit_v(self.charge);
        let r = spec.internal_resistance_ohm;
        let disc = e * e - 4.0 * power_w.max(0.0) * r;
        let v = if disc > 0.0 { 0.5 * (e + disc.sqrt()) } else { 0.5 * e };
        let i = if v > 0.0 { power_w.max(0.0) / v } else { 0.0 };
        self.voltage_v = v;
        self.current_a = i;
        self.charge = (self.charge - i * dt / (spec.capacity_mah * 3.6)).max(0.0);
    }

    /// The factor on rotor speed for this voltage: `V / V_cal` when the battery model is on,
    /// else 1.
    #[inline]
    pub fn speed_scale(&self, spec: &BatterySpec) -> Real {
        if spec.enabled { self.voltage_v / spec.calibration_voltage_v } else { 1.0 }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn open_circuit_voltage_spans_the_lipo_table() {
        let s = BatterySpec::default();
        assert!((s.open_circuit_v(1.0) - 12.6).abs() < 1e-4);
        assert!((s.open_circuit_v(0.0) - 9.81).abs() < 1e-4);
        assert!((s.open_circuit_v(0.525) - 3.0 * 3.845).abs() < 1e-4);
    }

    #[test]
    fn the_pack_sags_under_load_and_drains_by_the_charge_drawn() {
        let s = BatterySpec::default();
        let mut b = BatteryState::new(&s);
        // 50 W for 60 s.
        for _ in 0..6000 {
            b.draw(&s, 50.0, 0.01);
        }
        let e = s.open_circuit_v(b.charge);
        assert!((e - b.voltage_v - b.current_a * s.internal_resistance_ohm).abs() < 1e-3);
        let used_mah = (1.0 - b.charge) * s.capacity_mah;
        assert!((used_mah - 50.0 / 12.0 * 60.0 / 3.6).abs() < 5.0, "about 70 mAh: {used_mah}");
    }
}

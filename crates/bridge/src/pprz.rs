//! The simulator ↔ Paparazzi mapping: real copters' telemetry into twin commands, virtual sonar
//! readings back, and virtual copters' own telemetry, all in the Ivy text form of the project's
//! `assets/paparazzi/messages.xml`.
//!
//! **Frames.** Paparazzi's body frame is FRD and its attitude NED (`theta > 0` nose up,
//! `psi` clockwise). The simulator's body frame is FLU with ZYX Euler (`pitch > 0` nose down,
//! yaw counter-clockwise from +x). With the arena's +x as Paparazzi's north and +y as its west:
//! `roll = phi`, `pitch = −theta`, `yaw = −psi`. Positions: `north = x`, `east = −y`, `up = z`.

use crate::codec::{CodecError, Message, Sender};
use crate::messages::MessageSet;
use crate::value::Value;
use crate::wire::{CommandMsg, SensorsMsg, StateMsg};

/// The project's own message definitions (FINken telemetry, `ATTITUDE`, `ROTORCRAFT_FP`,
/// `VIRTUAL_SONAR`).
pub const MESSAGES_XML: &str = include_str!("../../../assets/paparazzi/messages.xml");

/// Parses [`MESSAGES_XML`].
pub fn project_messages() -> MessageSet {
    match MessageSet::parse(MESSAGES_XML, "assets/paparazzi/messages.xml") {
        Ok(m) => m,
        // Checked by a test; reaching this is a build defect.
        Err(e) => panic!("the embedded messages.xml is invalid: {e}"),
    }
}

/// Sonar value meaning "no virtual obstacle in range" in `VIRTUAL_SONAR`.
pub const NO_OBSTACLE_CM: u16 = u16::MAX;

fn f(msg: &Message<'_>, field: &str) -> Option<f32> {
    msg.get(field).and_then(Value::as_f64).map(|v| v as f32).filter(|v| v.is_finite())
}

/// What a real copter's telemetry message says about how to drive its twin, if anything.
///
/// - `FINKEN_ACTUATORS_SET_POINT` (deg, %): attitude targets and throttle;
/// - `FINKEN_SENSOR_MODEL` `pos_z` (m) and `FINKEN_IR_ADC` `ir_distance` (cm): the height to hold;
/// - `ATTITUDE` (rad), as fallback: attitude targets.
pub fn twin_command(msg: &Message<'_>) -> Option<CommandMsg> {
    match msg.def.name.as_str() {
        "FINKEN_ACTUATORS_SET_POINT" => Some(CommandMsg {
            pitch: f(msg, "pitch").map(|d| -d.to_radians()),
            roll: f(msg, "roll").map(f32::to_radians),
            yaw: f(msg, "yaw").map(|d| crate::pprz::wrap(-d.to_radians())),
            throttle: f(msg, "thrust").map(|p| (p / 100.0).clamp(0.0, 1.0)),
            ..CommandMsg::default()
        }),
        "FINKEN_SENSOR_MODEL" => {
            f(msg, "pos_z").filter(|z| *z > 0.0).map(|z| CommandMsg { height: Some(z), ..Default::default() })
        }
        "FINKEN_IR_ADC" => f(msg, "ir_distance")
            .filter(|cm| *cm > 0.0)
            .map(|cm| CommandMsg { height: Some(cm / 100.0), ..Default::default() }),
        "ATTITUDE" => Some(CommandMsg {
            pitch: f(msg, "theta").map(|t| -t),
            roll: f(msg, "phi"),
            yaw: f(msg, "psi").map(|p| wrap(-p)),
            ..CommandMsg::default()
        }),
        _ => None,
    }
}

fn wrap(a: f32) -> f32 {
    sim_core::math::wrap_angle_rad(a)
}

fn cm(m: f32) -> u16 {
    if !m.is_finite() || m < 0.0 { NO_OBSTACLE_CM } else { (m * 100.0).floor().min(65_534.0) as u16 }
}

/// `VIRTUAL_SONAR` for a real aircraft: virtual readings (front, right, back, left), m;
/// `INFINITY` for "nothing virtual in range".
pub fn virtual_sonar_text(messages: &MessageSet, ac_id: u8, readings_m: [f32; 4]) -> Result<String, CodecError> {
    let mut values = vec![Value::U8(ac_id)];
    values.extend(readings_m.iter().map(|&m| Value::U16(cm(m))));
    messages.encode(&Sender::ground(), "VIRTUAL_SONAR", &values)
}

/// Reads a `VIRTUAL_SONAR` message back into metres (`INFINITY` for no obstacle).
pub fn virtual_sonar_readings(msg: &Message<'_>) -> Option<(u8, [f32; 4])> {
    if msg.def.name != "VIRTUAL_SONAR" {
        return None;
    }
    let ac = msg.get("ac_id").and_then(Value::as_f64)? as u8;
    let mut out = [f32::INFINITY; 4];
    for (i, name) in ["front_cm", "right_cm", "back_cm", "left_cm"].iter().enumerate() {
        let v = msg.get(name).and_then(Value::as_f64)?;
        if v < f64::from(NO_OBSTACLE_CM) {
            out[i] = v as f32 / 100.0;
        }
    }
    Some((ac, out))
}

/// The telemetry a virtual copter publishes as aircraft `ac_id`, so ground tools see it:
/// `(message name, Ivy text)` for `SONAR_ARRAY`, `ATTITUDE`, `ROTORCRAFT_FP`,
/// `FINKEN_SENSOR_MODEL`.
pub fn virtual_telemetry(
    messages: &MessageSet,
    ac_id: u8,
    state: &StateMsg,
    sensors: Option<&SensorsMsg>,
) -> Vec<(&'static str, String)> {
    let sender = Sender::Aircraft(ac_id);
    let [roll, pitch, yaw] = state.attitude_rad;
    let (phi, theta, psi) = (roll, -pitch, wrap(-yaw));
    let [x, y, z] = state.pos_m;
    let [vx, vy, vz] = state.vel_m_s;
    let mut out = Vec::with_capacity(4);
    let mut push = |name: &'static str, values: Vec<Value>| match messages.encode(&sender, name, &values) {
        Ok(text) => out.push((name, text)),
        Err(e) => tracing::warn!("cannot encode {name}: {e}"),
    };
    push("ATTITUDE", vec![Value::F32(phi), Value::F32(psi), Value::F32(theta)]);
    let pos_i = |m: f32| Value::I32((m / 0.003_906_3) as i32);
    let vel_i = |m: f32| Value::I32((m / 0.000_001_9) as i32);
    let ang_i = |rad: f32| Value::I32((rad.to_degrees() / 0.013_988_2) as i32);
    let thrust: f32 = state.rotor_thrust_n.iter().sum();
    push(
        "ROTORCRAFT_FP",
        vec![
            pos_i(-y),
            pos_i(x),
            pos_i(z),
            vel_i(-vy),
            vel_i(vx),
            vel_i(vz),
            ang_i(phi),
            ang_i(theta),
            ang_i(psi),
            pos_i(-y),
            pos_i(x),
            pos_i(z),
            ang_i(psi),
            Value::I32((thrust * 1000.0) as i32),
            Value::U16(state.time_s.min(65_535.0) as u16),
        ],
    );
    if let Some(s) = sensors {
        let sonar = s.sonar_m;
        push(
            "SONAR_ARRAY",
            vec![
                Value::U16(cm(sonar.front)),
                Value::U16(cm(sonar.right)),
                Value::U16(cm(sonar.back)),
                Value::U16(cm(sonar.left)),
            ],
        );
        let [ax, ay, az] = s.accel_body_m_s2;
        push(
            "FINKEN_SENSOR_MODEL",
            vec![
                Value::U16(cm(sonar.front)),
                Value::U16(cm(sonar.right)),
                Value::U16(cm(sonar.left)),
                Value::U16(cm(sonar.back)),
                Value::I16(((sonar.front - sonar.back) * 100.0).clamp(-32_768.0, 32_767.0) as i16),
                Value::I16(((sonar.left - sonar.right) * 100.0).clamp(-32_768.0, 32_767.0) as i16),
                Value::F32(x),
                Value::F32(y),
                Value::F32(s.ir_m.unwrap_or(z)),
                Value::F32(theta),
                Value::F32(phi),
                Value::F32(psi),
                Value::F32(vx),
                Value::F32(vy),
                Value::F32(vz),
                Value::F32(-s.rate_body_rad_s[1]),
                Value::F32(s.rate_body_rad_s[0]),
                Value::F32(-s.rate_body_rad_s[2]),
                Value::F32(ax),
                Value::F32(ay),
                Value::F32(az),
            ],
        );
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_embedded_definitions_parse_and_have_what_the_bridge_uses() {
        let m = project_messages();
        for name in [
            "SONAR_ARRAY",
            "FINKEN_SENSOR_MODEL",
            "FINKEN_ACTUATORS_SET_POINT",
            "FINKEN_IR_ADC",
            "ATTITUDE",
            "ROTORCRAFT_FP",
            "VIRTUAL_SONAR",
        ] {
            assert!(m.by_name(name).is_some(), "{name}");
        }
    }

    #[test]
    fn actuator_set_points_become_twin_commands_in_the_simulators_frame() {
        let m = project_messages();
        let msg = m.decode("7 FINKEN_ACTUATORS_SET_POINT 10 -5 90 55").unwrap();
        let c = twin_command(&msg).unwrap();
        assert!((c.pitch.unwrap() + 10f32.to_radians()).abs() < 1e-6, "nose up in NED is nose up here: pitch < 0");
        assert!((c.roll.unwrap() + 5f32.to_radians()).abs() < 1e-6);
        assert!((c.yaw.unwrap() + 90f32.to_radians()).abs() < 1e-6, "clockwise psi is negative yaw");
        assert!((c.throttle.unwrap() - 0.55).abs() < 1e-6);
        let ir = m.decode("7 FINKEN_IR_ADC 80.5 512").unwrap();
        assert_eq!(twin_command(&ir).unwrap().height, Some(0.805));
        assert!(twin_command(&m.decode("7 SONAR_ARRAY 1 2 3 4").unwrap()).is_none());
    }

    #[test]
    fn virtual_sonar_round_trips_through_its_ivy_text() {
        let m = project_messages();
        let text = virtual_sonar_text(&m, 7, [1.234, f32::INFINITY, 0.5, 3.0]).unwrap();
        assert_eq!(text, "ground VIRTUAL_SONAR 7 123 65535 50 300");
        let (ac, back) = virtual_sonar_readings(&m.decode(&text).unwrap()).unwrap();
        assert_eq!(ac, 7);
        assert_eq!(back, [1.23, f32::INFINITY, 0.5, 3.0]);
    }
}

//! JSON messages on the bus: what the simulator publishes (clock, copter state, sensors) and
//! what it accepts (commands, spawn requests). Angles in radians, SI units, world frame as in
//! `sim-core` (x along the arena's long side, y across, z up; body FLU).

use serde::{Deserialize, Serialize};
use sim_core::sensors::SONAR_NAMES;
use sim_core::{Command, CopterKind, FlightMode, State, World};

/// Writes `f32` values as the `f64` of the same value. The shortest text of an `f32` is
/// exact only for a reader that parses it as an `f32`; Python and JavaScript parse JSON
/// numbers as `f64` and would round again, and a controller would then see another number
/// than the simulator has (a lockstep run would part from an in-process one).
mod exact {
    use serde::Serializer;
    use serde::ser::SerializeTuple;

    pub trait AsF64 {
        fn ser<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error>;
    }

    impl AsF64 for f32 {
        fn ser<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
            s.serialize_f64(f64::from(*self))
        }
    }

    impl AsF64 for Option<f32> {
        fn ser<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
            match self {
                Some(v) => s.serialize_some(&f64::from(*v)),
                None => s.serialize_none(),
            }
        }
    }

    impl<const N: usize> AsF64 for [f32; N] {
        fn ser<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
            let mut t = s.serialize_tuple(N)?;
            for v in self {
                t.serialize_element(&f64::from(*v))?;
            }
            t.end()
        }
    }

    pub fn serialize<T: AsF64, S: Serializer>(v: &T, s: S) -> Result<S::Ok, S::Error> {
        v.ser(s)
    }
}

/// Reads JSON numbers as `f64`, then rounds them to `f32`: what a client that computes in
/// `f64` (Python, JavaScript) means by a number is its `f64` value, and rounding that value
/// is what the Python package does with the same command. Parsing the text straight to `f32`
/// rounds the decimal instead, which now and then gives the neighbouring `f32`.
mod via_f64 {
    use serde::{Deserialize, Deserializer};

    pub trait FromF64: Sized {
        fn read<'de, D: Deserializer<'de>>(d: D) -> Result<Self, D::Error>;
    }

    impl FromF64 for Option<f32> {
        fn read<'de, D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
            Ok(Option::<f64>::deserialize(d)?.map(|v| v as f32))
        }
    }

    impl<const N: usize> FromF64 for Option<[f32; N]>
    where
        [f64; N]: for<'a> Deserialize<'a>,
    {
        fn read<'de, D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
            Ok(Option::<[f64; N]>::deserialize(d)?.map(|a| a.map(|v| v as f32)))
        }
    }

    pub fn deserialize<'de, T: FromF64, D: Deserializer<'de>>(d: D) -> Result<T, D::Error> {
        T::read(d)
    }
}

/// `…/clock`, every control step.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ClockMsg {
    /// Control steps done.
    pub tick: u64,
    /// Simulated time, s.
    pub time_s: f64,
}

/// `…/copters/<name>/state`, every control step.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct StateMsg {
    /// Copter name.
    pub name: String,
    /// `virtual` or `twin`.
    pub kind: String,
    /// Paparazzi aircraft id, if any.
    pub ac_id: Option<u8>,
    /// Control step.
    pub tick: u64,
    /// Simulated time, s.
    pub time_s: f64,
    /// Flight mode.
    pub mode: String,
    /// Position, world frame, m.
    #[serde(serialize_with = "exact::serialize")]
    pub pos_m: [f32; 3],
    /// Velocity, world frame, m/s.
    #[serde(serialize_with = "exact::serialize")]
    pub vel_m_s: [f32; 3],
    /// Roll, pitch, yaw (true attitude), rad.
    #[serde(serialize_with = "exact::serialize")]
    pub attitude_rad: [f32; 3],
    /// Angular velocity, world frame, rad/s.
    #[serde(serialize_with = "exact::serialize")]
    pub angvel_rad_s: [f32; 3],
    /// Orientation quaternion (x, y, z, w), world from body.
    #[serde(serialize_with = "exact::serialize")]
    pub quat_xyzw: [f32; 4],
    /// Rotor thrusts (front-left, front-right, back-right, back-left), N.
    #[serde(serialize_with = "exact::serialize")]
    pub rotor_thrust_n: [f32; 4],
    /// Whether it has crashed.
    pub crashed: bool,
}

/// Sonar readings by name, m.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct SonarMsg {
    /// Front (body +x).
    #[serde(serialize_with = "exact::serialize")]
    pub front: f32,
    /// Right (body −y).
    #[serde(serialize_with = "exact::serialize")]
    pub right: f32,
    /// Back (body −x).
    #[serde(serialize_with = "exact::serialize")]
    pub back: f32,
    /// Left (body +y).
    #[serde(serialize_with = "exact::serialize")]
    pub left: f32,
}

impl From<[f32; 4]> for SonarMsg {
    fn from(v: [f32; 4]) -> Self {
        debug_assert_eq!(SONAR_NAMES, ["front", "right", "back", "left"]);
        Self { front: v[0], right: v[1], back: v[2], left: v[3] }
    }
}

/// `…/copters/<name>/sensors`, at the sonar rate.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SensorsMsg {
    /// Copter name.
    pub name: String,
    /// Control step.
    pub tick: u64,
    /// Simulated time, s.
    pub time_s: f64,
    /// Physical sonar readings (noise, quantisation, cross-talk), m.
    pub sonar_m: SonarMsg,
    /// What the copter's behaviour uses: `min(physical, virtual)`, m.
    pub sonar_fused_m: SonarMsg,
    /// IR height, m; `null` when out of range.
    #[serde(serialize_with = "exact::serialize")]
    pub ir_m: Option<f32>,
    /// AHRS estimate: roll, pitch, yaw (with drift), rad.
    #[serde(serialize_with = "exact::serialize")]
    pub attitude_rad: [f32; 3],
    /// Gyro, body rates, rad/s.
    #[serde(serialize_with = "exact::serialize")]
    pub rate_body_rad_s: [f32; 3],
    /// Accelerometer, body frame, m/s².
    #[serde(serialize_with = "exact::serialize")]
    pub accel_body_m_s2: [f32; 3],
    /// The height estimate the copter holds (IR, filtered), m.
    #[serde(default)]
    #[serde(serialize_with = "exact::serialize")]
    pub height_est_m: f32,
    /// Battery voltage, V.
    #[serde(default)]
    #[serde(serialize_with = "exact::serialize")]
    pub battery_v: f32,
    /// Battery state of charge, in [0, 1].
    #[serde(default)]
    #[serde(serialize_with = "exact::serialize")]
    pub battery_charge: f32,
}

/// Builds the state message of copter `i`, flying `inputs`' command.
pub fn state_msg(world: &World, state: &State, inputs: &sim_core::Inputs, i: usize) -> StateMsg {
    let def = &world.copters[i];
    let c = &state.copters[i];
    let p = state.pose(i);
    StateMsg {
        name: def.name.clone(),
        kind: kind_str(def.kind).into(),
        ac_id: def.ac_id,
        tick: state.tick,
        time_s: state.time_s(world),
        mode: inputs.commands.get(i).map_or(def.initial_command.mode, |c| c.mode).as_str().into(),
        pos_m: p.pos_m.to_array(),
        vel_m_s: p.vel_m_s.to_array(),
        attitude_rad: p.rpy_rad,
        angvel_rad_s: p.angvel_rad_s.to_array(),
        quat_xyzw: p.quat_xyzw,
        rotor_thrust_n: c.rotor_thrust_n,
        crashed: c.crash.is_some(),
    }
}

/// Builds the sensors message of copter `i`.
pub fn sensors_msg(world: &World, state: &State, i: usize) -> SensorsMsg {
    let r = &state.copters[i].sensors;
    SensorsMsg {
        name: world.copters[i].name.clone(),
        tick: state.tick,
        time_s: state.time_s(world),
        sonar_m: r.sonar_m.into(),
        sonar_fused_m: r.sonar_fused_m.into(),
        ir_m: r.ir_m,
        attitude_rad: r.attitude_rad,
        rate_body_rad_s: r.rate_body_rad_s,
        accel_body_m_s2: r.accel_body_m_s2,
        height_est_m: r.height_est_m,
        battery_v: r.battery_v,
        battery_charge: r.battery_charge,
    }
}

/// The wire name of a copter kind.
pub fn kind_str(kind: CopterKind) -> &'static str {
    match kind {
        CopterKind::Virtual => "virtual",
        CopterKind::Real => "twin",
        CopterKind::Autopilot => "autopilot",
    }
}

/// `…/copters/<name>/cmd`: a command, every field optional. Unknown fields are rejected.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CommandMsg {
    /// `manual`, `mixed_manual`, `wall_avoid`, `target`, `velocity` or `rotors`.
    pub mode: Option<FlightMode>,
    /// Pitch target, rad (> 0: nose down, forward).
    #[serde(default, deserialize_with = "via_f64::deserialize")]
    pub pitch: Option<f32>,
    /// Roll target, rad (> 0: right side down, rightwards).
    #[serde(default, deserialize_with = "via_f64::deserialize")]
    pub roll: Option<f32>,
    /// Yaw target, rad, counter-clockwise from +x.
    #[serde(default, deserialize_with = "via_f64::deserialize")]
    pub yaw: Option<f32>,
    /// Throttle, 0 to 1 (0.5 = hover), used when no height is held.
    #[serde(default, deserialize_with = "via_f64::deserialize")]
    pub throttle: Option<f32>,
    /// Height to hold, m; 0 turns height hold off.
    #[serde(default, deserialize_with = "via_f64::deserialize")]
    pub height: Option<f32>,
    /// Target point for `target` mode, m.
    #[serde(default, deserialize_with = "via_f64::deserialize")]
    pub target: Option<[f32; 3]>,
    /// Velocity, body frame (forward, left), m/s: flown open loop in `velocity` mode, and
    /// when safe in `wall_avoid`.
    #[serde(default, deserialize_with = "via_f64::deserialize")]
    pub velocity: Option<[f32; 2]>,
    /// Virtual sonar readings to fuse as `min(physical, virtual)`, m (front, right, back, left).
    #[serde(default, deserialize_with = "via_f64::deserialize")]
    pub virtual_sonar: Option<[f32; 4]>,
    /// Rotor commands for `rotors` mode, each 0 to 1 of the rotor's maximum thrust
    /// (front-left, front-right, back-right, back-left).
    #[serde(default, skip_serializing_if = "Option::is_none", deserialize_with = "via_f64::deserialize")]
    pub rotors: Option<[f32; 4]>,
    /// Lockstep (`run --lockstep`): the tick of the state this command answers. A command of
    /// only `{"tick": t}` keeps the last command (see `docs/lockstep.md`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub tick: Option<u64>,
    /// Who sends it: the client name of its liveliness claim
    /// `…/alive/copters/<name>/<client>`. A copter that a client has claimed takes commands
    /// from that client only (see [`crate::zenoh_net::node`]).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub client: Option<String>,
}

/// Why a command was rejected.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum CommandError {
    /// Not JSON, or not a command.
    #[error("malformed command: {0}")]
    Malformed(String),
    /// A field is NaN or infinite.
    #[error("field `{0}` is not a finite number")]
    NotFinite(&'static str),
    /// A field is out of its range.
    #[error("field `{field}` = {value} is out of range [{min}, {max}]")]
    OutOfRange {
        /// The field.
        field: &'static str,
        /// Its value.
        value: f32,
        /// Lower bound.
        min: f32,
        /// Upper bound.
        max: f32,
    },
    /// No such copter.
    #[error("no copter named {0:?}")]
    UnknownCopter(String),
}

impl CommandMsg {
    /// Parses and validates a command payload against the world.
    pub fn parse(payload: &[u8], world: &World) -> Result<Self, CommandError> {
        let cmd: CommandMsg = serde_json::from_slice(payload).map_err(|e| CommandError::Malformed(e.to_string()))?;
        cmd.validate(world)?;
        Ok(cmd)
    }

    /// Checks every field is finite and in range.
    pub fn validate(&self, world: &World) -> Result<(), CommandError> {
        use std::f32::consts::{FRAC_PI_2, PI};
        let range = |field: &'static str, v: f32, min: f32, max: f32| -> Result<(), CommandError> {
            if !v.is_finite() {
                return Err(CommandError::NotFinite(field));
            }
            if v < min || v > max {
                return Err(CommandError::OutOfRange { field, value: v, min, max });
            }
            Ok(())
        };
        let [hx, hy] = world.arena.size_m.map(|s| s / 2.0);
        if let Some(v) = self.pitch {
            range("pitch", v, -FRAC_PI_2, FRAC_PI_2)?;
        }
        if let Some(v) = self.roll {
            range("roll", v, -FRAC_PI_2, FRAC_PI_2)?;
        }
        if let Some(v) = self.yaw {
            range("yaw", v, -2.0 * PI, 2.0 * PI)?;
        }
        if let Some(v) = self.throttle {
            range("throttle", v, 0.0, 1.0)?;
        }
        if let Some(v) = self.height {
            range("height", v, 0.0, world.arena.height_m)?;
        }
        if let Some([x, y, z]) = self.target {
            range("target", x, -hx, hx)?;
            range("target", y, -hy, hy)?;
            range("target", z, 0.0, world.arena.height_m)?;
        }
        if let Some(v) = self.velocity {
            for c in v {
                range("velocity", c, -5.0, 5.0)?;
            }
        }
        if let Some(v) = self.virtual_sonar {
            for c in v {
                range("virtual_sonar", c, 0.0, 100.0)?;
            }
        }
        if let Some(v) = self.rotors {
            for c in v {
                range("rotors", c, 0.0, 1.0)?;
            }
        }
        Ok(())
    }

    /// Applies the fields that are set onto a copter's command.
    pub fn apply(&self, cmd: &mut Command) {
        if let Some(m) = self.mode {
            cmd.mode = m;
        }
        if let Some(v) = self.pitch {
            cmd.pitch_rad = v;
        }
        if let Some(v) = self.roll {
            cmd.roll_rad = v;
        }
        if let Some(v) = self.yaw {
            cmd.yaw_rad = v;
        }
        if let Some(v) = self.throttle {
            cmd.throttle = v;
        }
        if let Some(v) = self.height {
            cmd.height_m = v;
        }
        if let Some(v) = self.target {
            cmd.target_m = Some(v);
        }
        if let Some(v) = self.velocity {
            cmd.velocity_m_s = Some(v);
        }
        if let Some(v) = self.virtual_sonar {
            cmd.virtual_sonar_m = Some(v);
        }
        if let Some(v) = self.rotors {
            cmd.rotors = Some(v);
        }
    }
}

/// `…/copters/<name>/tracking`: an external pose of a twin's real copter (e.g. from a camera
/// system), world frame. It describes the copter a configured lag ago (see [`crate::mixed::sync`]).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TrackingMsg {
    /// Position, m: `[x, y]` or `[x, y, z]` (z is not used).
    pub pos_m: Vec<f32>,
    /// Heading, rad (not used yet).
    #[serde(default)]
    pub yaw_rad: Option<f32>,
}

impl TrackingMsg {
    /// Parses and checks a tracking payload: 2 or 3 finite coordinates within 100 m.
    pub fn parse(payload: &[u8]) -> Result<Self, CommandError> {
        let t: TrackingMsg = serde_json::from_slice(payload).map_err(|e| CommandError::Malformed(e.to_string()))?;
        if !(2..=3).contains(&t.pos_m.len()) {
            return Err(CommandError::Malformed(format!("pos_m has {} values, expected 2 or 3", t.pos_m.len())));
        }
        for &v in &t.pos_m {
            if !v.is_finite() {
                return Err(CommandError::NotFinite("pos_m"));
            }
            if v.abs() > 100.0 {
                return Err(CommandError::OutOfRange { field: "pos_m", value: v, min: -100.0, max: 100.0 });
            }
        }
        Ok(t)
    }
}

/// One entry of the `…/copters` queryable's reply.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CopterListEntry {
    /// Copter id.
    pub id: usize,
    /// Name.
    pub name: String,
    /// `virtual` or `twin`.
    pub kind: String,
    /// Paparazzi aircraft id.
    pub ac_id: Option<u8>,
    /// Whether it has crashed.
    pub crashed: bool,
}

#[cfg(test)]
mod tests {
    use super::*;

    fn world() -> World {
        sim_core::scene::load_default().1
    }

    #[test]
    fn commands_parse_validate_and_apply() {
        let w = world();
        let c = CommandMsg::parse(br#"{"mode":"target","height":1.0,"target":[0.5,0.2,1.0]}"#, &w).unwrap();
        let mut cmd = Command::default();
        c.apply(&mut cmd);
        assert_eq!(cmd.mode, FlightMode::Target);
        assert_eq!(cmd.target_m, Some([0.5, 0.2, 1.0]));
        assert_eq!(cmd.height_m, 1.0);
    }

    #[test]
    fn malformed_nan_and_out_of_range_commands_are_rejected() {
        let w = world();
        assert!(matches!(CommandMsg::parse(b"not json", &w), Err(CommandError::Malformed(_))));
        assert!(matches!(CommandMsg::parse(br#"{"pitchh":0.1}"#, &w), Err(CommandError::Malformed(_))));
        assert!(matches!(CommandMsg::parse(br#"{"mode":"loop"}"#, &w), Err(CommandError::Malformed(_))));
        // JSON has no NaN literal: a NaN arrives as a string or null and is malformed.
        assert!(matches!(CommandMsg::parse(br#"{"pitch":"NaN"}"#, &w), Err(CommandError::Malformed(_))));
        let nan = CommandMsg { pitch: Some(f32::NAN), ..Default::default() };
        assert_eq!(nan.validate(&w), Err(CommandError::NotFinite("pitch")));
        assert!(matches!(
            CommandMsg::parse(br#"{"throttle":1.5}"#, &w),
            Err(CommandError::OutOfRange { field: "throttle", .. })
        ));
        assert!(matches!(
            CommandMsg::parse(br#"{"height":9.0}"#, &w),
            Err(CommandError::OutOfRange { field: "height", .. })
        ));
        assert!(matches!(
            CommandMsg::parse(br#"{"target":[9,0,1]}"#, &w),
            Err(CommandError::OutOfRange { field: "target", .. })
        ));
    }
}

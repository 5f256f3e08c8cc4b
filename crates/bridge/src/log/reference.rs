//! The reference for the hand-written per-step JSON: the same messages as serde structs,
//! serialised by serde_json. The test encodes real steps both ways and wants the same bytes.

use serde::Serialize;
use serde::ser::{SerializeSeq, Serializer};
use sim_core::control::FlightMode;
use sim_core::{CopterKind, CrashCause, World};

use super::super::capture::{CopterSample, StepFrame};
use super::super::msg::*;
use super::{Encoder, SONAR_AXES, SONAR_Z_TO_AXIS, SonarGeometry, Topic, WORLD_FRAME};

/// `twinswarm.CopterState`.
#[derive(Debug, Serialize)]
pub(crate) struct StateMsg<'a> {
    pub tick: u64,
    pub t_s: f64,
    pub copter: &'a str,
    pub id: usize,
    pub ac_id: Option<u8>,
    pub kind: CopterKind,
    pub mode: FlightMode,
    pub crashed: bool,
    pub crash_cause: Option<&'a CrashCause>,
    pub took_off: bool,
    pub pos_m: [f32; 3],
    pub vel_m_s: [f32; 3],
    pub rpy_rad: [f32; 3],
    pub angvel_rad_s: [f32; 3],
    pub quat_xyzw: [f32; 4],
    pub rotor_thrust_n: [f32; 4],
    pub rotor_speed_rad_s: [f32; 4],
}

/// `twinswarm.CopterSensors`.
#[derive(Debug, Serialize)]
pub(crate) struct SensorsMsg<'a> {
    pub tick: u64,
    pub t_s: f64,
    pub copter: &'a str,
    pub id: usize,
    pub sonar_tick: u64,
    pub sonar_truth_m: [f32; 4],
    pub sonar_m: [f32; 4],
    pub sonar_fused_m: [f32; 4],
    pub sonar_crosstalk: [bool; 4],
    pub ir_m: Option<f32>,
    pub ir_truth_m: Option<f32>,
    pub attitude_rad: [f32; 3],
    pub yaw_bias_rad: f32,
    pub rate_body_rad_s: [f32; 3],
    pub accel_body_m_s2: [f32; 3],
    pub height_est_m: f32,
    pub battery_v: f32,
    pub battery_charge: f32,
    pub battery_a: f32,
}

/// `twinswarm.CopterCommand`.
#[derive(Debug, Serialize)]
pub(crate) struct CommandMsg<'a> {
    pub tick: u64,
    pub t_s: f64,
    pub copter: &'a str,
    pub id: usize,
    pub mode: FlightMode,
    pub roll_rad: f32,
    pub pitch_rad: f32,
    pub yaw_rad: f32,
    pub throttle: f32,
    pub height_m: f32,
    pub target_m: Option<[f32; 3]>,
    pub velocity_m_s: Option<[f32; 2]>,
    pub virtual_sonar_m: Option<[f32; 4]>,
}

/// `twinswarm.CopterControl`.
#[derive(Debug, Serialize)]
pub(crate) struct ControlMsg<'a> {
    pub tick: u64,
    pub t_s: f64,
    pub copter: &'a str,
    pub id: usize,
    pub setpoint: &'a sim_core::Setpoint,
    pub wall_avoid: WallAvoidMsg,
}

#[derive(Debug, Serialize)]
pub(crate) struct WallAvoidMsg {
    pub engaged: bool,
    pub out_rad: [f32; 2],
    pub last_m: [f32; 4],
    pub rate_m_s: [f32; 4],
}

/// `foxglove.FrameTransform`.
#[derive(Debug, Serialize)]
pub(crate) struct FrameTransform<'a> {
    pub timestamp: Time,
    pub parent_frame_id: &'a str,
    pub child_frame_id: &'a str,
    pub translation: V3,
    pub rotation: Q,
}

/// Every per-step message of `frame`, as serde writes them (events excluded).
pub(super) fn encode_step(enc: &Encoder, world: &World, frame: &StepFrame) -> Vec<(Topic, u64, Vec<u8>)> {
    let tick = frame.tick;
    let lt = enc.log_time(tick);
    let t_s = enc.t_s(tick);
    let mut out = Vec::new();
    let mut emit = |topic, msg: &dyn erased::Ser| out.push((topic, lt, msg.to_vec()));
    for (id, (wc, c)) in world.copters.iter().zip(&frame.copters).enumerate() {
        let name = wc.name.as_str();
        let mode = c.command.mode;
        let p = &c.pose;
        emit(
            Topic::State,
            &StateMsg {
                tick,
                t_s,
                copter: name,
                id,
                ac_id: wc.ac_id,
                kind: wc.kind,
                mode,
                crashed: c.crash.is_some(),
                crash_cause: c.crash.as_ref(),
                took_off: c.took_off_tick.is_some(),
                pos_m: p.pos_m.into(),
                vel_m_s: p.vel_m_s.into(),
                rpy_rad: p.rpy_rad,
                angvel_rad_s: p.angvel_rad_s.into(),
                quat_xyzw: p.quat_xyzw,
                rotor_thrust_n: c.rotor_thrust_n,
                rotor_speed_rad_s: c.rotor_speed_rad_s,
            },
        );
        let r = &c.sensors;
        emit(
            Topic::Sensors,
            &SensorsMsg {
                tick,
                t_s,
                copter: name,
                id,
                sonar_tick: r.sonar_tick,
                sonar_truth_m: r.sonar_truth_m,
                sonar_m: r.sonar_m,
                sonar_fused_m: r.sonar_fused_m,
                sonar_crosstalk: r.sonar_crosstalk,
                ir_m: r.ir_m,
                ir_truth_m: r.ir_truth_m.is_finite().then_some(r.ir_truth_m),
                attitude_rad: r.attitude_rad,
                yaw_bias_rad: r.yaw_bias_rad,
                rate_body_rad_s: r.rate_body_rad_s,
                accel_body_m_s2: r.accel_body_m_s2,
                height_est_m: r.height_est_m,
                battery_v: r.battery_v,
                battery_charge: r.battery_charge,
                battery_a: r.battery_a,
            },
        );
        let cmd = &c.command;
        emit(
            Topic::Command,
            &CommandMsg {
                tick,
                t_s,
                copter: name,
                id,
                mode,
                roll_rad: cmd.roll_rad,
                pitch_rad: cmd.pitch_rad,
                yaw_rad: cmd.yaw_rad,
                throttle: cmd.throttle,
                height_m: cmd.height_m,
                target_m: cmd.target_m,
                velocity_m_s: cmd.velocity_m_s,
                virtual_sonar_m: cmd.virtual_sonar_m,
            },
        );
        let wa = &c.wall_avoid;
        emit(
            Topic::Control,
            &ControlMsg {
                tick,
                t_s,
                copter: name,
                id,
                setpoint: &c.setpoint,
                wall_avoid: WallAvoidMsg {
                    engaged: mode == FlightMode::WallAvoid && wa.out_rad != [0.0; 2],
                    out_rad: wa.out_rad,
                    last_m: wa.last_m,
                    rate_m_s: wa.rate_m_s,
                },
            },
        );
        emit(
            Topic::Tf,
            &FrameTransform {
                timestamp: Time::from_ns(lt),
                parent_frame_id: WORLD_FRAME,
                child_frame_id: name,
                translation: v3(p.pos_m.x, p.pos_m.y, p.pos_m.z),
                rotation: Q { x: p.quat_xyzw[0], y: p.quat_xyzw[1], z: p.quat_xyzw[2], w: p.quat_xyzw[3] },
            },
        );
    }
    if tick.is_multiple_of(enc.scene_every_ticks()) {
        let entities = CopterEntities { world, frame, sonar: enc.sonar, time: Time::from_ns(lt) };
        emit(Topic::SceneCopters, &SceneUpdate { deletions: [], entities });
    }
    out
}

mod erased {
    /// A serialisable message behind a `dyn`.
    pub trait Ser {
        fn to_vec(&self) -> Vec<u8>;
    }
    impl<T: serde::Serialize> Ser for T {
        fn to_vec(&self) -> Vec<u8> {
            serde_json::to_vec(self).expect("plain structs serialise")
        }
    }
}

/// The per-step copter entities.
struct CopterEntities<'a> {
    world: &'a World,
    frame: &'a StepFrame,
    sonar: SonarGeometry,
    time: Time,
}

impl Serialize for CopterEntities<'_> {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        let mut seq = s.serialize_seq(Some(self.world.copters.len()))?;
        for (wc, c) in self.world.copters.iter().zip(&self.frame.copters) {
            let c: &CopterSample = c;
            let [bx, by, bz] = self.world.airframes[wc.airframe].spec.body_size_m;
            let body_color = match (c.crash.is_some(), wc.kind) {
                (true, _) => rgba(0.85, 0.1, 0.1, 1.0),
                (false, CopterKind::Real) => rgba(0.1, 0.6, 0.2, 1.0),
                (false, CopterKind::Virtual) => rgba(0.15, 0.35, 0.8, 1.0),
            };
            let cube = [Cube {
                pose: Pose { position: V3::default(), orientation: IDENTITY },
                size: v3(bx, by, bz),
                color: body_color,
            }];
            let g = self.sonar;
            let cones: [Cylinder; 4] = std::array::from_fn(|k| {
                let reading = c.sensors.sonar_fused_m[k];
                let echo = reading < g.cap_m;
                let len = reading.clamp(g.min_m, g.cap_m);
                let color = if c.sensors.sonar_crosstalk[k] {
                    rgba(1.0, 0.55, 0.0, 0.45)
                } else if !echo {
                    rgba(0.5, 0.5, 0.5, 0.06)
                } else if reading < g.safety_m {
                    rgba(0.9, 0.2, 0.2, 0.3)
                } else {
                    rgba(0.2, 0.6, 1.0, 0.2)
                };
                let a = SONAR_AXES[k];
                let d = g.mount_offset_m + len / 2.0;
                let width = 2.0 * len * g.tan_half;
                Cylinder {
                    pose: Pose { position: v3(a[0] * d, a[1] * d, a[2] * d), orientation: SONAR_Z_TO_AXIS[k] },
                    size: v3(width, width, len),
                    bottom_scale: 0.0,
                    top_scale: 1.0,
                    color,
                }
            });
            let entity_id = format!("copter/{}", wc.name);
            seq.serialize_element(&Entity {
                timestamp: self.time,
                frame_id: &wc.name,
                id: &entity_id,
                lifetime: FOREVER,
                frame_locked: true,
                metadata: &[],
                arrows: &[],
                cubes: &cube,
                spheres: [],
                cylinders: &cones,
                lines: &[],
                triangles: [],
                texts: &[],
                models: [],
            })?;
        }
        seq.end()
    }
}

#[test]
fn hand_written_json_equals_serde() {
    use sim_core::{CrashCause, step};
    // Two copters of the default lab, one of them given every optional command field, and a
    // third that has crashed: every branch of the writer.
    let (mut spec, _) = sim_core::scene::load_default();
    spec.copters.push(spec.copters[0].clone());
    spec.copters[2].name = "crash-test_3".into();
    spec.copters[2].ac_id = None;
    spec.copters[1].kind = sim_core::CopterKind::Real;
    spec.copters[2].start.pos_m[0] += 0.5;
    let world = sim_core::scene::compile(&spec).expect("the default scene compiles");
    let mut state = world.initial_state();
    let mut inputs = world.initial_inputs();
    inputs.commands[1].target_m = Some([0.1, -0.2, 0.8]);
    inputs.commands[1].velocity_m_s = Some([0.3, f32::NAN]);
    inputs.commands[1].virtual_sonar_m = Some([1.0, 2.0, f32::INFINITY, 0.3]);
    let mut enc = Encoder::new(&world, 1_790_000_000_123_456_789);
    let mut frame = StepFrame::default();
    let mut compared = 0;
    for k in 0..40 {
        let report = step(&world, &mut state, &inputs);
        if k == 30 {
            state.copters[2].crash = Some(CrashCause::Floor { speed_m_s: 2.5 });
        }
        frame.capture(&world, &state, &inputs, &report);
        frame.events.clear();
        let want = encode_step(&enc, &world, &frame);
        let mut got = Vec::new();
        enc.encode_step(&frame, &mut |t, lt, d: &[u8]| {
            got.push((t, lt, d.to_vec()));
            Ok::<_, ()>(())
        })
        .expect("a Vec sink cannot fail");
        assert_eq!(got.len(), want.len(), "tick {}", frame.tick);
        for (g, w) in got.iter().zip(&want) {
            assert_eq!((g.0, g.1), (w.0, w.1));
            assert_eq!(
                String::from_utf8_lossy(&g.2),
                String::from_utf8_lossy(&w.2),
                "{:?} at tick {}",
                g.0,
                frame.tick
            );
            compared += 1;
        }
    }
    assert!(compared > 40 * 15, "compared {compared} messages");
    let _: Option<CrashCause> = None;
}

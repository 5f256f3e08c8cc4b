//! Everything that changes during a run: the [`State`], and a fresh one from the
//! [`World`] ([`World::initial_state`]).

use std::sync::Mutex;

use rapier3d::prelude::{
    ColliderBuilder, ColliderHandle, ColliderSet, CollisionEvent, ContactPair, EventHandler, InteractionGroups,
    MassProperties, PhysicsWorld, RigidBodyBuilder, RigidBodyHandle, RigidBodySet, SoftBodySet, SoftBodyTearEvent,
};
use serde::{Deserialize, Serialize};

use crate::battery::BatteryState;
use crate::control::{PidState, Setpoint, WallAvoidState};
use crate::estimate::Estimate;
use crate::geometry::OrientedBox;
use crate::math::{GRAVITY_M_S2, Quat, Real, Vec3, Vector, euler_from_quat};
use crate::rng::Rng32;
use crate::sensors::{CopterGrid, SensorReadings, SonarScene};
use crate::world::{ColliderTag, VIRTUAL_ONLY_BOX, World};

/// A fresh [`State`] from the [`World`]: its static geometry and copters as Rapier bodies.
impl World {
    /// A fresh state at tick 0: static geometry, copters at their start poses, seeded RNGs.
    pub fn initial_state(&self) -> State {
        let mut physics = PhysicsWorld::new();
        physics.gravity = Vector::new(0.0, 0.0, -GRAVITY_M_S2);
        physics.integration_parameters.dt = self.physics_dt();
        // No continuous collision detection: at 5 ms a copter moves at most a few cm, less
        // than the walls' and floor's thickness; CCD's sweeps cost more than the rest of a
        // wreck's step.
        physics.integration_parameters.max_ccd_substeps = 0;
        self.insert_static_geometry(&mut physics);
        let mut state = State { tick: 0, physics, copters: Vec::new(), scratch: Scratch::default(), shard: None };
        for id in 0..self.copters.len() {
            let copter = self.make_copter(&mut state.physics, id);
            state.copters.push(copter);
        }
        state
    }

    fn insert_static_geometry(&self, physics: &mut PhysicsWorld) {
        let t = self.arena.wall_thickness_m;
        let [sx, sy] = self.arena.size_m;
        let h = self.arena.height_m;
        // Each on a fixed body of its own: a copter's contacts with two of them are then two body
        // pairs, coloured in body-id order (see `World::copter_collider_of`).
        let add = |physics: &mut PhysicsWorld, half: Vec3, center: Vec3, yaw: Real, tag: ColliderTag| {
            let ground = physics.insert_body(RigidBodyBuilder::fixed());
            let virtual_only = matches!(tag, ColliderTag::Box(i) if self.boxes[i].virtual_only);
            let collider = ColliderBuilder::cuboid(half.x, half.y, half.z)
                .translation(center)
                .rotation(Vec3::new(0.0, 0.0, yaw))
                .friction(0.8)
                .collision_groups(if virtual_only { VIRTUAL_ONLY_BOX } else { InteractionGroups::all() })
                .user_data(tag.encode());
            physics.insert_collider(collider, Some(ground));
        };
        add(
            physics,
            Vec3::new(sx / 2.0 + t, sy / 2.0 + t, t / 2.0),
            Vec3::new(0.0, 0.0, -t / 2.0),
            0.0,
            ColliderTag::Floor,
        );
        if self.arena.walls {
            let hz = h / 2.0;
            add(
                physics,
                Vec3::new(t / 2.0, sy / 2.0 + t, hz),
                Vec3::new(sx / 2.0 + t / 2.0, 0.0, hz),
                0.0,
                ColliderTag::Wall,
            );
            add(
                physics,
                Vec3::new(t / 2.0, sy / 2.0 + t, hz),
                Vec3::new(-sx / 2.0 - t / 2.0, 0.0, hz),
                0.0,
                ColliderTag::Wall,
            );
            add(
                physics,
                Vec3::new(sx / 2.0 + t, t / 2.0, hz),
                Vec3::new(0.0, sy / 2.0 + t / 2.0, hz),
                0.0,
                ColliderTag::Wall,
            );
            add(
                physics,
                Vec3::new(sx / 2.0 + t, t / 2.0, hz),
                Vec3::new(0.0, -sy / 2.0 - t / 2.0, hz),
                0.0,
                ColliderTag::Wall,
            );
            add(
                physics,
                Vec3::new(sx / 2.0 + t, sy / 2.0 + t, t / 2.0),
                Vec3::new(0.0, 0.0, h + t / 2.0),
                0.0,
                ColliderTag::Ceiling,
            );
        }
        for (i, b) in self.boxes.iter().enumerate() {
            add(physics, b.half_extents_m, b.center_m, b.yaw_rad, ColliderTag::Box(i));
        }
    }

    /// Creates copter `id`'s rigid body and colliders and its initial runtime state.
    pub(crate) fn make_copter(&self, physics: &mut PhysicsWorld, id: usize) -> CopterState {
        let def = &self.copters[id];
        let af = &self.airframes[def.airframe];
        let [ix, iy, iz] = af.inertia_kg_m2;
        let body = RigidBodyBuilder::dynamic()
            .translation(def.start_pos_m)
            .rotation(Vec3::new(0.0, 0.0, def.start_yaw_rad))
            .linear_damping(af.spec.linear_damping)
            .angular_damping(af.spec.angular_damping)
            .additional_mass_properties(MassProperties::new(Vec3::ZERO, af.mass_kg, Vec3::new(ix, iy, iz)))
            .can_sleep(false)
            .user_data(id as u128);
        let handle = physics.insert_body(body);
        let collider = physics.insert_collider(self.copter_collider_of(id), Some(handle));
        CopterState::new(self, id, handle, collider)
    }
}

/// The mutable state of a run: physics sets, controller integrators, rotor states, sensor
/// memory, random streams and the tick.
///
/// **Invariant:** a `State` serialised and restored, then stepped, gives the same bytes as the
/// uninterrupted run. Only [`Scratch`] (work buffers) is left out of snapshots.
#[derive(Serialize, Deserialize)]
pub struct State {
    /// Completed control steps. Simulated time is `tick × control_dt`.
    pub tick: u64,
    /// Rapier's sets, islands, broad and narrow phase.
    pub physics: PhysicsWorld,
    /// Per-copter state, indexed by copter id.
    pub copters: Vec<CopterState>,
    /// Work buffers, rebuilt as needed; not part of snapshots.
    #[serde(skip)]
    pub(crate) scratch: Scratch,
    /// Its place in a sharded run ([`crate::shard`]); `None`: it steps every copter.
    #[serde(skip)]
    pub(crate) shard: Option<crate::partition::ShardView>,
}

impl std::fmt::Debug for State {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("State")
            .field("tick", &self.tick)
            .field("bodies", &self.physics.bodies.len())
            .field("colliders", &self.physics.colliders.len())
            .field("copters", &self.copters)
            .finish_non_exhaustive()
    }
}

/// Why a copter crashed.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum CrashCause {
    /// It touched a wall.
    Wall,
    /// It touched the ceiling.
    Ceiling,
    /// It touched a static box.
    Box {
        /// Index of the box.
        index: usize,
    },
    /// It hit the floor too fast.
    Floor {
        /// Impact speed, m/s.
        speed_m_s: Real,
    },
    /// It hit another copter too fast.
    Copter {
        /// The other copter's id.
        other: usize,
        /// Relative speed, m/s.
        speed_m_s: Real,
    },
    /// It tilted beyond the crash tilt.
    Tilt {
        /// Tilt, deg.
        tilt_deg: Real,
    },
}

/// Runtime state of one copter.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct CopterState {
    /// Its rigid body.
    pub body: RigidBodyHandle,
    /// Its main (body box) collider.
    pub collider: ColliderHandle,
    /// Seeded manufacturing tolerance of each rotor's thrust (1 = nominal; always 1 for twins).
    pub rotor_tolerance: [Real; 4],
    /// The trim: a constant body torque (roll, pitch) that cancels the rotors' tolerances at
    /// hover, N·m (0 when untrimmed, and for twins).
    #[serde(default)]
    pub trim_torque_n_m: [Real; 2],
    /// Rotor speeds, rad/s.
    pub rotor_speed_rad_s: [Real; 4],
    /// Rotor thrusts applied in the last physics step, N.
    pub rotor_thrust_n: [Real; 4],
    /// Attitude PIDs: roll, pitch, yaw.
    pub pids: [PidState; 3],
    /// The outer loop's output for the current control step.
    pub setpoint: Setpoint,
    /// Wall-Avoid memory.
    pub wall_avoid: WallAvoidState,
    /// Latest sensor readings.
    pub sensors: SensorReadings,
    /// The AHRS yaw bias, a random walk, rad.
    pub yaw_bias_rad: Real,
    /// Velocity at the previous control step (for the accelerometer), m/s.
    pub prev_vel_m_s: Vec3,
    /// Estimators: height, attitude, rates, thrust gain. What the controllers read.
    pub estimate: Estimate,
    /// The flight battery.
    pub battery: BatteryState,
    /// Time of one of its sonars' pings, s (free-running cross-talk).
    pub sonar_phase_s: f64,
    /// Its sonars' ranging cycle, s.
    pub sonar_cycle_s: f64,
    /// Set once it has crashed; its motors stay off.
    #[serde(with = "crash_snapshot")]
    pub crash: Option<CrashCause>,
    /// Tick it first left the floor.
    pub took_off_tick: Option<u64>,
    /// Resting level on the floor, held there in closed form (see `step`): before take-off,
    /// after a landing. Only meaningful while it flies free of Rapier. For a wreck in closed
    /// form: it has come to rest (on the floor, a box or another wreck) for good.
    #[serde(default)]
    pub grounded: bool,
    /// Its random stream.
    pub rng: Rng32,
    /// Its pose and velocities at the end of the last step: the truth everything reads. Its
    /// Rapier body follows only while Rapier steps it (near something, or a wreck).
    pub motion: Motion,
}

/// A crash cause in a snapshot: `(kind, speed or tilt, index)` rather than [`CrashCause`]'s
/// tagged form (logs and JSON keep that one), which positional formats such as postcard cannot
/// read back.
pub(crate) mod crash_snapshot {
    use super::{CrashCause, Real};
    use serde::{Deserialize, Deserializer, Serialize, Serializer};

    type Raw = Option<(u8, Real, u64)>;

    pub fn serialize<S: Serializer>(crash: &Option<CrashCause>, s: S) -> Result<S::Ok, S::Error> {
        let raw: Raw = crash.map(|c| match c {
            CrashCause::Wall => (0, 0.0, 0),
            CrashCause::Ceiling => (1, 0.0, 0),
            CrashCause::Box { index } => (2, 0.0, index as u64),
            CrashCause::Floor { speed_m_s } => (3, speed_m_s, 0),
            CrashCause::Copter { other, speed_m_s } => (4, speed_m_s, other as u64),
            CrashCause::Tilt { tilt_deg } => (5, tilt_deg, 0),
        });
        raw.serialize(s)
    }

    pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<Option<CrashCause>, D::Error> {
        let raw = Raw::deserialize(d)?;
        raw.map(|(kind, v, i)| match kind {
            0 => Ok(CrashCause::Wall),
            1 => Ok(CrashCause::Ceiling),
            2 => Ok(CrashCause::Box { index: i as usize }),
            3 => Ok(CrashCause::Floor { speed_m_s: v }),
            4 => Ok(CrashCause::Copter { other: i as usize, speed_m_s: v }),
            5 => Ok(CrashCause::Tilt { tilt_deg: v }),
            k => Err(serde::de::Error::custom(format!("unknown crash kind {k} in a snapshot"))),
        })
        .transpose()
    }
}

/// The roll and pitch trim of a copter whose rotors make `tolerance` times their nominal
/// thrust: the body torque command that levels it at hover, in commands at a thrust gain of 1
/// (the inner loop divides it by the current gain), N·m. Found as a lab trims by flying: the
/// command is corrected by the torque the rotors then actually make until that is zero (the
/// mixer's own response to the trim goes through the tolerant rotors too).
pub fn trim_torque(af: &crate::airframe::Airframe, tolerance: [Real; 4]) -> [Real; 2] {
    let mean = tolerance.iter().sum::<Real>() / 4.0;
    let collective = 4.0 * af.hover_thrust_per_rotor_n / mean;
    let mut trim = Vec3::ZERO;
    for _ in 0..8 {
        let f = crate::control::mix(af, collective, trim);
        let mut made = Vec3::ZERO;
        for ((p, tol), f) in af.rotor_pos_in_body_m.iter().zip(tolerance).zip(f) {
            made += p.cross(Vec3::new(0.0, 0.0, tol * f));
        }
        trim -= Vec3::new(made.x, made.y, 0.0);
    }
    [trim.x * mean, trim.y * mean]
}

impl CopterState {
    /// FNV-1a over the bits of its motion, rotor speeds, battery charge, crash and the next
    /// draw of its random stream: two runs whose copters have equal digests flew the same bits.
    pub fn digest(&self) -> u64 {
        let m = &self.motion;
        let mut h: u64 = 0xcbf2_9ce4_8422_2325;
        let mut put = |bits: u32| {
            for b in bits.to_le_bytes() {
                h = (h ^ u64::from(b)).wrapping_mul(0x0000_0100_0000_01b3);
            }
        };
        for v in [m.pos_m, m.vel_m_s, m.angvel_rad_s] {
            v.to_array().into_iter().for_each(|x| put(x.to_bits()));
        }
        m.rot.to_array().into_iter().for_each(|x| put(x.to_bits()));
        self.rotor_speed_rad_s.into_iter().for_each(|x| put(x.to_bits()));
        put(self.battery.charge.to_bits());
        put(u32::from(self.crash.is_some()));
        put(self.rng.clone().uniform().to_bits());
        h
    }
}

/// A copter's pose and velocities, world frame.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Motion {
    /// Centre of mass, m.
    pub pos_m: Vec3,
    /// World-from-body rotation.
    pub rot: Quat,
    /// Velocity, m/s.
    pub vel_m_s: Vec3,
    /// Angular velocity, rad/s.
    pub angvel_rad_s: Vec3,
}

impl CopterState {
    pub(crate) fn new(world: &World, id: usize, body: RigidBodyHandle, collider: ColliderHandle) -> Self {
        let af = &world.airframes[world.copters[id].airframe];
        let mut rng = Rng32::new(world.params.seed, id as u64);
        let sigma = af.spec.rotor_tolerance_sigma;
        let drawn: [Real; 4] = std::array::from_fn(|_| (1.0 + sigma * rng.normal()).max(0.5));
        // A twin's rotors are nominal: its real copter's imperfections are unknown here, and
        // its motion comes from that copter's telemetry. (Drawn anyway: same random stream.)
        let rotor_tolerance = if world.copters[id].kind == crate::CopterKind::Real { [1.0; 4] } else { drawn };
        let cmd = &world.copters[id].initial_command;
        let def = &world.copters[id];
        let ct = &world.sensors.spec.crosstalk;
        let (sonar_phase_s, sonar_cycle_s) = match ct.phase {
            crate::sensors::CrosstalkPhase::Synchronous => (0.0, f64::from(ct.cycle_s)),
            crate::sensors::CrosstalkPhase::FreeRunning => {
                let cycle = f64::from(ct.cycle_s) * f64::from(1.0 + ct.cycle_spread * rng.normal()).max(0.5);
                (f64::from(rng.uniform()) * cycle, cycle)
            }
        };
        let mut estimate = Estimate::new(&world.sensors.spec.estimator, def.start_pos_m.z, def.start_yaw_rad, &mut rng);
        // The IMU's mounting error, drawn whether or not the calibration cancels it (the same
        // random stream either way).
        let mount_sigma = af.spec.imu_mount_sigma_deg.to_radians();
        let mount = [mount_sigma * rng.normal(), mount_sigma * rng.normal()];
        let twin = world.copters[id].kind == crate::CopterKind::Real;
        let (trim_torque_n_m, mount) = if af.spec.trimmed || twin {
            (if twin { [0.0; 2] } else { trim_torque(af, rotor_tolerance) }, [0.0; 2])
        } else {
            ([0.0; 2], mount)
        };
        estimate.mount_offset_rad = mount;
        Self {
            body,
            collider,
            rotor_tolerance,
            trim_torque_n_m,
            rotor_speed_rad_s: [0.0; 4],
            rotor_thrust_n: [0.0; 4],
            pids: [PidState::default(); 3],
            setpoint: Setpoint { yaw_rad: cmd.yaw_rad, ..Setpoint::default() },
            wall_avoid: WallAvoidState::default(),
            sensors: SensorReadings::default(),
            yaw_bias_rad: 0.0,
            prev_vel_m_s: Vec3::ZERO,
            estimate,
            battery: BatteryState::new(&af.spec.battery),
            sonar_phase_s,
            sonar_cycle_s,
            crash: None,
            took_off_tick: None,
            motion: Motion {
                pos_m: def.start_pos_m,
                rot: Quat::from_rotation_z(def.start_yaw_rad),
                vel_m_s: Vec3::ZERO,
                angvel_rad_s: Vec3::ZERO,
            },
            grounded: def.start_pos_m.z <= af.rest_height_m + 1e-4,
            rng,
        }
    }
}

/// A copter's pose and motion, read from the physics.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct CopterPose {
    /// Position of the centre of mass, world frame, m.
    pub pos_m: Vec3,
    /// Velocity, world frame, m/s.
    pub vel_m_s: Vec3,
    /// Roll, pitch, yaw (true), rad.
    pub rpy_rad: [Real; 3],
    /// Angular velocity, world frame, rad/s.
    pub angvel_rad_s: Vec3,
    /// World-from-body rotation (x, y, z, w).
    pub quat_xyzw: [Real; 4],
}

impl State {
    /// Pose of copter `id`.
    pub fn pose(&self, id: usize) -> CopterPose {
        let m = &self.copters[id].motion;
        let q = m.rot;
        CopterPose {
            pos_m: m.pos_m,
            vel_m_s: m.vel_m_s,
            rpy_rad: euler_from_quat(q),
            angvel_rad_s: m.angvel_rad_s,
            quat_xyzw: [q.x, q.y, q.z, q.w],
        }
    }

    /// The downwash force copter `id` felt in the last step (world frame), N: the thrust the
    /// wakes of the others cost its rotors.
    pub fn downwash_force_n(&self, id: usize) -> Vec3 {
        self.scratch.lanes.get(id).map_or(Vec3::ZERO, |l| l.downwash_force_n)
    }

    /// Adds the bodies and runtime state of copters that `world` has and this state does not
    /// yet (after [`World::with_spawned`]). Existing copters are untouched.
    pub fn add_copters(&mut self, world: &World) {
        for id in self.copters.len()..world.copters.len() {
            let copter = world.make_copter(&mut self.physics, id);
            self.copters.push(copter);
        }
    }

    /// Moves copter `id` horizontally by `delta_m` (x, y), keeping its velocity and attitude:
    /// how a bridge corrects a twin's position (bounded steps, never teleports). Explicit, so
    /// determinism holds: the same shifts give the same run.
    pub fn shift_copter(&mut self, id: usize, delta_m: [Real; 2]) {
        let Some(c) = self.copters.get_mut(id) else { return };
        if !delta_m.iter().all(|v| v.is_finite()) {
            return;
        }
        let p = &mut c.motion.pos_m;
        *p = Vec3::new(p.x + delta_m[0], p.y + delta_m[1], p.z);
        if let Some(b) = self.physics.bodies.get_mut(c.body)
            && b.is_enabled()
        {
            b.set_translation(*p, true);
        }
    }

    /// Simulated time, s.
    pub fn time_s(&self, world: &World) -> f64 {
        world.time_at(self.tick)
    }
}

/// Collects collision starts during a physics step.
#[derive(Debug, Default)]
pub(crate) struct CollisionCollector {
    pub(crate) started: Mutex<Vec<(ColliderHandle, ColliderHandle)>>,
}

impl EventHandler for CollisionCollector {
    fn handle_collision_event(
        &self,
        _bodies: &RigidBodySet,
        _colliders: &ColliderSet,
        event: CollisionEvent,
        _contact_pair: Option<&ContactPair>,
    ) {
        if let CollisionEvent::Started(a, b, _) = event
            && let Ok(mut v) = self.started.lock()
        {
            v.push((a, b));
        }
    }

    fn handle_contact_force_event(
        &self,
        _dt: Real,
        _bodies: &RigidBodySet,
        _colliders: &ColliderSet,
        _contact_pair: &ContactPair,
        _total_force_magnitude: Real,
    ) {
    }

    fn handle_soft_body_tear_event(&self, _soft_bodies: &SoftBodySet, _event: &SoftBodyTearEvent) {}
}

/// Work buffers reused from step to step, so a warm step does not allocate.
#[derive(Debug, Default)]
pub(crate) struct Scratch {
    pub(crate) collisions: CollisionCollector,
    pub(crate) started: Vec<(ColliderHandle, ColliderHandle)>,
    /// The owned copters in Rapier (not flying free), in id order: the ones whose forces go
    /// into Rapier's step and whose motion comes out of it. Room for every copter.
    pub(crate) in_rapier: Vec<u32>,
    pub(crate) sonar_scene: SonarScene,
    /// What the sonars of a real-layer copter flying on physics (an outside autopilot's) see:
    /// no virtual copters, no `virtual_only` boxes. Filled only when such a copter exists.
    pub(crate) real_scene: SonarScene,
    /// The ids the real scene indexes, ascending.
    pub(crate) real_ids: Vec<u32>,
    /// Every copter's sonar cones and ping timing, for cross-talk.
    pub(crate) pingers: Vec<Pinger>,
    /// The positions of the copters that ping (flyers), and their grid: wrecks are silent, so
    /// the cross-talk pass need not visit them.
    pub(crate) ping_points: Vec<(u32, Vec3)>,
    pub(crate) ping_grid: CopterGrid,
    /// One lane per copter: its motion during the step and its free-flight reservation.
    pub(crate) lanes: Vec<Lane>,
    /// Reserved spheres of all copters (radius in `half.x`), for the free-flight test.
    pub(crate) spheres: Vec<OrientedBox>,
    /// A grid over `spheres`.
    pub(crate) sphere_grid: CopterGrid,
    /// This shard's wrecks falling in closed form, by id (see `step::fall_wrecks`).
    pub(crate) falling: Vec<u32>,
    /// Per falling wreck (as `falling`): its substep from the substep's start, found in
    /// parallel, and whether it came to rest (see `step::fall_wrecks`).
    pub(crate) wreck_moves: Vec<(Lane, bool)>,
    /// The wrecks that came to rest in the current substep, in id order.
    pub(crate) landed: Vec<u32>,
    /// Per chunk of [`step::ALERT_CHUNK`] lanes: whether one of them may have crashed, taken
    /// off or left its reservation in the last substep (see `step::detect_tilt_and_takeoff`).
    pub(crate) alerts: Vec<bool>,
    /// On one thread, the owned copters that did not run ahead to the step's end, in id order
    /// (listed after the first substep's pass, `step::list_between`): the only ones the later
    /// substeps step, and the only ones the substeps between the first and the last check
    /// (`step::detect_tilt_and_takeoff`). With threads, every substep scans all the lanes in
    /// parallel (the list would be made on one thread).
    pub(crate) between: Vec<u32>,
    /// Per copter: whether its Rapier body is enabled, disabled or taken over this step (see
    /// `step::enable_rapier_bodies`), found in parallel, changed in id order.
    pub(crate) body_changes: Vec<bool>,
    /// Copters on watch and what they may meet this step, (on watch, other) once per pair.
    pub(crate) watch_pairs: Vec<(u32, u32)>,
    /// cos of each airframe's crash tilt.
    pub(crate) crash_cos_tilt: Vec<Real>,
    /// Each airframe's motor-lag blend factor for one physics step.
    pub(crate) motor_alpha: Vec<Real>,
    /// Every copter's wake this control step.
    pub(crate) wakes: Vec<crate::airflow::Wake>,
    /// The wakes' reach (radius in `half.x`), for `wake_grid`.
    pub(crate) wake_reach: Vec<OrientedBox>,
    /// A grid over `wake_reach`.
    pub(crate) wake_grid: CopterGrid,
    /// Ids of the copters a shard reads (owned and ghosts), ascending; empty outside a
    /// sharded run.
    pub(crate) present: Vec<u32>,
    /// Worker threads (`World::params.threads` > 1), built on first use.
    pub(crate) pool: Option<rayon::ThreadPool>,
}

/// A copter's sonars as an emitter of pings: its centre, cones and ping timing.
#[derive(Clone, Copy, Debug, Default)]
pub(crate) struct Pinger {
    pub(crate) pos_m: Vec3,
    pub(crate) cones: [crate::geometry::Cone; 4],
    pub(crate) phase_s: f64,
    pub(crate) cycle_s: f64,
    /// Whether it pings at all (a wreck does not).
    pub(crate) pings: bool,
}

/// A copter's motion during one control step, and whether it flies free of Rapier.
#[derive(Clone, Copy, Debug, Default)]
pub(crate) struct Lane {
    /// Centre of mass, world frame, m.
    pub(crate) pos_m: Vec3,
    /// World-from-body rotation.
    pub(crate) rot: Quat,
    /// Velocity, world frame, m/s.
    pub(crate) vel_m_s: Vec3,
    /// Angular velocity, world frame, rad/s.
    pub(crate) angvel_rad_s: Vec3,
    /// Force and torque (world frame) for Rapier to apply this substep, N and N·m.
    pub(crate) force_n: Vec3,
    pub(crate) torque_n_m: Vec3,
    /// Flies free this control step: integrated in closed form, its Rapier body disabled.
    pub(crate) free: bool,
    /// Flies free but near other copters: each substep checks whether it may touch one, and
    /// if so hands it to Rapier (see `step::watch_contacts`).
    pub(crate) watch: bool,
    /// In a shard: its reservation sphere meets another copter's (see `step::take_ownership`).
    pub(crate) touching: bool,
    /// Bounding radius plus the reach of its acceleration within one substep, m.
    pub(crate) substep_reserved_m: Real,
    /// Centre of the reservation at the start of the step, m.
    pub(crate) anchor_m: Vec3,
    /// How far the centre may move during the step and stay free, m.
    pub(crate) reach_m: Real,
    /// Bounding radius of the copter's colliders plus `reach_m`, m.
    pub(crate) reserved_m: Real,
    /// Height of the surface below each rotor (floor or box top), m, for ground effect.
    pub(crate) ground_m: [Real; 4],
    /// Speed at which it hit the floor in free flight this substep, too fast to land (a
    /// crash for the serial pass to record), m/s; 0 if none.
    pub(crate) floor_impact_m_s: Real,
    /// Downwash force on the copter this control step, world frame, N.
    pub(crate) downwash_force_n: Vec3,
    /// Its torque about the centre of mass, world frame, N·m.
    pub(crate) downwash_torque_n_m: Vec3,
    /// Its airframe's index (a copy of `CopterDef::airframe`, for the serial passes).
    pub(crate) airframe: u32,
    /// Not crashed (cleared at its crash within the step).
    pub(crate) flying: bool,
    /// Not crashed and not yet taken off.
    pub(crate) awaiting_takeoff: bool,
    /// Velocity before this substep's contacts (after its free flight or fall), m/s: the
    /// impact speed of a crash.
    pub(crate) vel_before_m_s: Vec3,
    /// Substeps of this control step it has run ahead of the others (flying free off watch:
    /// see `step::step_copters`).
    pub(crate) batched: u32,
}

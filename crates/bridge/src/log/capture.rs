//! What the stepping thread copies out of a step: numbers only, into reused buffers.

use sim_core::control::WallAvoidState;
use sim_core::{Command, CopterPose, CrashCause, Event, Inputs, SensorReadings, Setpoint, State, StepReport, World};

/// One copter after a control step: its pose, rotors, controller outputs, readings and the
/// command it flew.
#[derive(Clone, Debug, PartialEq)]
pub struct CopterSample {
    /// Pose and motion at the end of the step.
    pub pose: CopterPose,
    /// Rotor thrusts in the last physics substep, N.
    pub rotor_thrust_n: [f32; 4],
    /// Rotor speeds, rad/s.
    pub rotor_speed_rad_s: [f32; 4],
    /// The outer loop's setpoint for the step.
    pub setpoint: Setpoint,
    /// Wall-Avoid memory and PD output.
    pub wall_avoid: WallAvoidState,
    /// Readings used in the step.
    pub sensors: SensorReadings,
    /// Crash, if it has crashed.
    pub crash: Option<CrashCause>,
    /// Tick it took off.
    pub took_off_tick: Option<u64>,
    /// The command applied during the step.
    pub command: Command,
    /// Stepped by this process (always, unless it is one shard of a sharded run: then only
    /// its own copters are logged).
    pub owned: bool,
}

/// Everything logged about one control step. Reused from step to step (its vectors keep
/// their capacity), so capturing does not allocate once warm.
#[derive(Clone, Debug, Default)]
pub struct StepFrame {
    /// The tick reached by the step.
    pub tick: u64,
    /// One sample per copter, in id order.
    pub copters: Vec<CopterSample>,
    /// Events of the step.
    pub events: Vec<Event>,
}

impl StepFrame {
    /// Copies what is logged out of a step just taken.
    pub fn capture(&mut self, world: &World, state: &State, inputs: &Inputs, report: &StepReport) {
        self.tick = state.tick;
        self.copters.clear();
        for (i, c) in state.copters.iter().enumerate() {
            let command = inputs.commands.get(i).unwrap_or(&world.copters[i].initial_command);
            self.copters.push(CopterSample {
                pose: state.pose(i),
                rotor_thrust_n: c.rotor_thrust_n,
                rotor_speed_rad_s: c.rotor_speed_rad_s,
                setpoint: c.setpoint,
                wall_avoid: c.wall_avoid,
                sensors: c.sensors,
                crash: c.crash,
                took_off_tick: c.took_off_tick,
                command: command.clone(),
                owned: state.owns(i),
            });
        }
        self.events.clear();
        self.events.extend_from_slice(&report.events);
    }
}

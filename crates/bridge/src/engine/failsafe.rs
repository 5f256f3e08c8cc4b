//! Lost links: what a copter does when whoever drives it goes quiet.
//!
//! Two kinds of copter are driven from outside, and each can lose its driver:
//!
//! - **A twin** follows its real copter's telemetry. PX4's data-link-loss failsafe is the
//!   model (`COM_DL_LOSS_T`, then `NAV_DLL_ACT`): after [`FailsafeOptions::hold_after_s`] of
//!   silence, or [`HOLD_PERIODS`] of its aircraft's own telemetry period if that is longer (the
//!   median gap of its last [`GAP_WINDOW`] inputs: an NPS rotorcraft's default telemetry drives
//!   a twin every 250 ms, with gaps of 560 ms at p99, and must not trip a 0.5 s failsafe), the
//!   twin levels out and holds its height (it would otherwise fly on with the
//!   last attitude it was given); after [`FailsafeOptions::land_after_s`] it descends at
//!   [`FailsafeOptions::descent_m_s`]; once down it stops steering (level, Wall-Avoid off),
//!   and once it has rested on the floor for [`SETTLE_S`] its motors stop. When telemetry comes back, at any point, it follows again.
//! - **A virtual copter commanded over Zenoh** has a controller: the client whose liveliness
//!   claim came first (see [`crate::zenoh_net::node`]). When that client's token disappears
//!   (the process died, the network went), the copter does what
//!   [`FailsafeOptions::client_lost`] says: hover where it is, land, or go back to its scene
//!   mode. A command from its next controller ends the failsafe.
//!
//! Silence is measured on the wall clock, as telemetry and liveliness live on it; the
//! transitions themselves are applied on the loop thread, between steps, and each one is a
//! [`FailsafeEvent`] for the log.

use std::collections::BTreeMap;
use std::time::Instant;

use sim_core::control::{Command, FlightMode};
use sim_core::{Inputs, State, World};

/// A twin holds after this many of its aircraft's telemetry periods of silence, if that is
/// longer than [`FailsafeOptions::hold_after_s`].
pub const HOLD_PERIODS: f64 = 4.0;
/// How many recent gaps between a twin's inputs make its telemetry period (their median).
pub const GAP_WINDOW: usize = 32;

/// The recent gaps between a twin's telemetry inputs, s, and their median.
#[derive(Clone, Debug, Default)]
struct Period {
    gaps: std::collections::VecDeque<f64>,
    median_s: f64,
}

impl Period {
    fn record(&mut self, gap_s: f64) {
        if self.gaps.len() == GAP_WINDOW {
            self.gaps.pop_front();
        }
        self.gaps.push_back(gap_s);
        let mut v: Vec<f64> = self.gaps.iter().copied().collect();
        v.sort_by(f64::total_cmp);
        self.median_s = v[v.len() / 2];
    }
}

/// A copter resting this long on the floor while landing stops its motors, s.
pub const SETTLE_S: f64 = 0.5;
/// Height above its resting height below which a landing copter counts as down, m.
const TOUCHDOWN_M: f32 = 0.02;
/// How far below its resting height a landing copter aims, so that it presses onto the floor
/// instead of hovering just above it, m.
const PRESS_M: f32 = 0.05;

/// What a virtual copter does when its controlling client disappears.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ClientLostAction {
    /// Level out and hold the present height.
    #[default]
    Hover,
    /// Descend and land, as a twin does.
    Land,
    /// Go back to the copter's command from the scene file.
    Scene,
}

impl std::str::FromStr for ClientLostAction {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "hover" => Ok(Self::Hover),
            "land" => Ok(Self::Land),
            "scene" => Ok(Self::Scene),
            other => Err(format!("unknown action {other:?}: expected hover, land or scene")),
        }
    }
}

/// Failsafe timings and actions.
#[derive(Clone, Debug, PartialEq)]
pub struct FailsafeOptions {
    /// A twin whose telemetry has been silent this long levels out and holds its height, s.
    pub hold_after_s: f64,
    /// A twin whose telemetry has been silent this long descends and lands, s.
    pub land_after_s: f64,
    /// Descent rate while landing, m/s.
    pub descent_m_s: f32,
    /// What a virtual copter does when its controlling client disappears.
    pub client_lost: ClientLostAction,
}

impl Default for FailsafeOptions {
    /// Hold after 0.5 s (the twin's sample period is 22 ms: that is 20 lost in a row); land
    /// after 5 s (PX4's `COM_DL_LOSS_T` default is 10 s outdoors; an indoor arena is small);
    /// descend at 0.3 m/s (PX4's `MPC_LAND_SPEED` is 0.7 m/s, for larger craft); a lost
    /// client's copter hovers.
    fn default() -> Self {
        Self { hold_after_s: 0.5, land_after_s: 5.0, descent_m_s: 0.3, client_lost: ClientLostAction::Hover }
    }
}

impl FailsafeOptions {
    /// Checks the values: finite, positive, landing after holding.
    pub fn validate(&self) -> Result<(), String> {
        if !(self.hold_after_s.is_finite() && self.hold_after_s > 0.0) {
            return Err(format!("link-loss hold time must be positive, got {} s", self.hold_after_s));
        }
        if !(self.land_after_s.is_finite() && self.land_after_s >= self.hold_after_s) {
            return Err(format!(
                "link-loss landing time must be at least the hold time ({} s), got {} s",
                self.hold_after_s, self.land_after_s
            ));
        }
        if !(self.descent_m_s.is_finite() && self.descent_m_s > 0.0 && self.descent_m_s <= 2.0) {
            return Err(format!("descent rate must be in (0, 2] m/s, got {}", self.descent_m_s));
        }
        Ok(())
    }
}

/// What happened to a copter's link, for the log and the summary.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum FailsafeKind {
    /// A twin's telemetry stopped: it levels out and holds its height.
    Hold {
        /// Silence so far, s.
        silent_s: f64,
    },
    /// It descends to land.
    Land {
        /// Silence so far, s (twins), or 0 for a lost client.
        silent_s: f64,
    },
    /// It rests on the floor with its motors off.
    Landed,
    /// Its driver is back (telemetry, or a new controller's command): it follows again.
    Resumed {
        /// Silence it had, s.
        silent_s: f64,
    },
    /// The client controlling it disappeared.
    ClientLost {
        /// That client.
        client: String,
        /// What the copter does now.
        action: ClientLostAction,
    },
    /// A client took control of it, or the last one let go (`client: None`).
    Controller {
        /// The new controller.
        client: Option<String>,
    },
}

impl FailsafeKind {
    /// A short name: `hold`, `land`, `landed`, `resumed`, `client_lost`, `controller`.
    pub fn name(&self) -> &'static str {
        match self {
            Self::Hold { .. } => "hold",
            Self::Land { .. } => "land",
            Self::Landed => "landed",
            Self::Resumed { .. } => "resumed",
            Self::ClientLost { .. } => "client_lost",
            Self::Controller { .. } => "controller",
        }
    }
}

/// One transition of one copter.
#[derive(Clone, Debug, PartialEq)]
pub struct FailsafeEvent {
    /// The copter, by id.
    pub copter: usize,
    /// What happened.
    pub kind: FailsafeKind,
}

impl FailsafeEvent {
    /// A line for humans.
    pub fn message(&self, world: &World) -> String {
        let name = world.copters.get(self.copter).map_or("?", |c| c.name.as_str());
        match &self.kind {
            FailsafeKind::Hold { silent_s } => {
                format!("{name}: no telemetry for {silent_s:.2} s; levelling out, holding its height")
            }
            FailsafeKind::Land { silent_s } if *silent_s > 0.0 => {
                format!("{name}: no telemetry for {silent_s:.2} s; landing")
            }
            FailsafeKind::Land { .. } => format!("{name}: landing"),
            FailsafeKind::Landed => format!("{name}: landed, motors off"),
            FailsafeKind::Resumed { silent_s } => format!("{name}: link back after {silent_s:.2} s; following again"),
            FailsafeKind::ClientLost { client, action } => {
                format!("{name}: its controller {client:?} disappeared; {action:?}")
            }
            FailsafeKind::Controller { client: Some(c) } => format!("{name}: now controlled by {c:?}"),
            FailsafeKind::Controller { client: None } => format!("{name}: no controller"),
        }
    }
}

#[derive(Clone, Copy, Debug, PartialEq)]
enum Phase {
    Holding,
    /// Descending towards `target_m` (height-hold target, lowered each step).
    Landing {
        target_m: f32,
    },
    /// Down since `since` (wall clock), motors on, level (no steering), pressing onto the
    /// floor.
    Settling {
        since: Instant,
    },
    Landed,
}

#[derive(Clone, Debug)]
struct Guard {
    phase: Phase,
    /// The command before the failsafe took over, restored when the driver is back.
    saved: Command,
}

/// The failsafes of every copter, on the loop thread.
#[derive(Debug, Default)]
pub struct Failsafe {
    opts: FailsafeOptions,
    /// Twins: when their last telemetry input applied.
    last_input: BTreeMap<usize, Instant>,
    /// Twins: their telemetry period as it arrives.
    periods: BTreeMap<usize, Period>,
    guards: BTreeMap<usize, Guard>,
    /// Transitions so far, by [`FailsafeKind::name`].
    pub counts: BTreeMap<&'static str, u64>,
}

impl Failsafe {
    /// Failsafes with these options.
    pub fn new(opts: FailsafeOptions) -> Self {
        Self { opts, ..Default::default() }
    }

    /// Whether copter `id` is under a failsafe now.
    pub fn active(&self, id: usize) -> bool {
        self.guards.contains_key(&id)
    }

    fn push(&mut self, events: &mut Vec<FailsafeEvent>, copter: usize, kind: FailsafeKind) {
        record(&mut self.counts, events, copter, kind);
    }

    /// A twin's telemetry input applied at `now`: it is a driven copter from now on (a twin
    /// with no input yet has no failsafe), and a failsafe it was under ends (the command from
    /// before it restored) before the input applies.
    pub fn telemetry(&mut self, id: usize, now: Instant, inputs: &mut Inputs, events: &mut Vec<FailsafeEvent>) {
        let last = self.last_input.insert(id, now);
        let silent_s = last.map_or(0.0, |t| now.duration_since(t).as_secs_f64());
        // A gap that ended a failsafe is an outage, not the aircraft's period.
        if last.is_some() && !self.guards.contains_key(&id) {
            self.periods.entry(id).or_default().record(silent_s);
        }
        self.resume(id, silent_s, inputs, events);
    }

    /// How long twin `id` may be silent before it holds, s: [`FailsafeOptions::hold_after_s`],
    /// or [`HOLD_PERIODS`] of its telemetry period if longer.
    pub fn hold_after_s(&self, id: usize) -> f64 {
        let period = self.periods.get(&id).map_or(0.0, |p| p.median_s);
        self.opts.hold_after_s.max(HOLD_PERIODS * period)
    }

    /// A command from a client (after a lost controller, a new one takes over): ends a
    /// failsafe, restoring the command from before it, before the command applies. Commands
    /// do not make a copter timed: clients need not send them continuously.
    pub fn commanded(&mut self, id: usize, inputs: &mut Inputs, events: &mut Vec<FailsafeEvent>) {
        self.resume(id, 0.0, inputs, events);
    }

    fn resume(&mut self, id: usize, silent_s: f64, inputs: &mut Inputs, events: &mut Vec<FailsafeEvent>) {
        if let Some(g) = self.guards.remove(&id) {
            inputs.commands[id] = g.saved;
            self.push(events, id, FailsafeKind::Resumed { silent_s });
        }
    }

    /// A controlling client disappeared: apply [`FailsafeOptions::client_lost`].
    pub fn client_lost(
        &mut self,
        world: &World,
        state: &State,
        id: usize,
        client: &str,
        inputs: &mut Inputs,
        events: &mut Vec<FailsafeEvent>,
    ) {
        let action = self.opts.client_lost;
        self.push(events, id, FailsafeKind::ClientLost { client: client.to_owned(), action });
        // It is no longer a driven copter: only a new command ends this.
        self.last_input.remove(&id);
        self.periods.remove(&id);
        match action {
            ClientLostAction::Scene => inputs.commands[id] = world.copters[id].initial_command.clone(),
            ClientLostAction::Hover => take_over(&mut self.guards, state, id, inputs, Phase::Holding),
            ClientLostAction::Land => {
                let target_m = state.pose(id).pos_m.z;
                take_over(&mut self.guards, state, id, inputs, Phase::Landing { target_m });
                self.push(events, id, FailsafeKind::Land { silent_s: 0.0 });
            }
        }
    }

    /// After a step: twins silent too long enter their failsafe, landings go on.
    pub fn after_step(
        &mut self,
        world: &World,
        state: &State,
        inputs: &mut Inputs,
        now: Instant,
        events: &mut Vec<FailsafeEvent>,
    ) {
        let dt = world.params.control_dt_s as f32;
        // Disjoint fields: no copy of the silent twins on this per-step path.
        let Self { opts, last_input, periods, guards, counts } = self;
        for (&id, &t) in last_input.iter() {
            let silent_s = now.saturating_duration_since(t).as_secs_f64();
            let period = periods.get(&id).map_or(0.0, |p| p.median_s);
            if silent_s <= opts.hold_after_s.max(HOLD_PERIODS * period) || id >= inputs.commands.len() {
                continue;
            }
            if !guards.contains_key(&id) {
                take_over(guards, state, id, inputs, Phase::Holding);
                record(counts, events, id, FailsafeKind::Hold { silent_s });
            }
            if silent_s > opts.land_after_s
                && let Some(g) = guards.get_mut(&id)
                && g.phase == Phase::Holding
            {
                g.phase = Phase::Landing { target_m: state.pose(id).pos_m.z };
                record(counts, events, id, FailsafeKind::Land { silent_s });
            }
        }
        for (&id, g) in guards.iter_mut() {
            let rest = world.airframes[world.copters[id].airframe].rest_height_m;
            let z = state.pose(id).pos_m.z;
            let cmd = &mut inputs.commands[id];
            match g.phase {
                Phase::Holding | Phase::Landed => {}
                Phase::Landing { target_m } => {
                    let target_m = (target_m - opts.descent_m_s * dt).max(rest - PRESS_M);
                    cmd.height_m = target_m.max(1e-3);
                    g.phase = if z <= rest + TOUCHDOWN_M {
                        // Down: no more steering. Wall-Avoid's pushes would tilt a copter
                        // that sits on its thrust and skid it along the floor into whatever
                        // it was avoiding (a landing crashed into the lab's crate that way).
                        cmd.mode = FlightMode::MixedManual;
                        (cmd.roll_rad, cmd.pitch_rad) = (0.0, 0.0);
                        Phase::Settling { since: now }
                    } else {
                        Phase::Landing { target_m }
                    };
                }
                Phase::Settling { since } => {
                    if z > rest + 2.0 * TOUCHDOWN_M {
                        g.phase = Phase::Landing { target_m: rest };
                    } else if now.saturating_duration_since(since).as_secs_f64() >= SETTLE_S {
                        // On the floor: stop the motors (height hold off, zero throttle).
                        (cmd.height_m, cmd.throttle) = (0.0, 0.0);
                        g.phase = Phase::Landed;
                        record(counts, events, id, FailsafeKind::Landed);
                    }
                }
            }
        }
    }

    /// A controller event (for the counts and the log).
    pub fn controller(&mut self, id: usize, client: Option<String>, events: &mut Vec<FailsafeEvent>) {
        self.push(events, id, FailsafeKind::Controller { client });
    }
}

/// The failsafe takes copter `id` over in `phase`: its command is kept for later, and it
/// levels out at the height it has now.
fn take_over(guards: &mut BTreeMap<usize, Guard>, state: &State, id: usize, inputs: &mut Inputs, phase: Phase) {
    let saved = inputs.commands[id].clone();
    level_and_hold(&mut inputs.commands[id], state.pose(id).pos_m.z);
    guards.insert(id, Guard { phase, saved });
}

/// Counts a transition and hands it on.
fn record(
    counts: &mut BTreeMap<&'static str, u64>,
    events: &mut Vec<FailsafeEvent>,
    copter: usize,
    kind: FailsafeKind,
) {
    *counts.entry(kind.name()).or_default() += 1;
    events.push(FailsafeEvent { copter, kind });
}

/// Level, no steering, holding height `z_m`; a copter lower than 5 cm (on the floor) stays
/// there, motors off, rather than lifting off into ground effect. A Wall-Avoid copter keeps
/// avoiding what its sonars see (as a real FINken's autopilot would: the avoidance runs on
/// board) but stops cruising; any other mode becomes level flight.
fn level_and_hold(cmd: &mut Command, z_m: f32) {
    if cmd.mode != FlightMode::WallAvoid {
        cmd.mode = FlightMode::MixedManual;
    }
    (cmd.roll_rad, cmd.pitch_rad) = (0.0, 0.0);
    cmd.velocity_m_s = None;
    cmd.target_m = None;
    if z_m < 0.05 {
        (cmd.height_m, cmd.throttle) = (0.0, 0.0);
    } else {
        cmd.height_m = z_m;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    #[test]
    fn client_lost_actions_parse() {
        assert_eq!("land".parse::<ClientLostAction>(), Ok(ClientLostAction::Land));
        assert!("fly".parse::<ClientLostAction>().unwrap_err().contains("hover, land or scene"));
        assert!(FailsafeOptions::default().validate().is_ok());
        let bad = FailsafeOptions { land_after_s: 0.1, ..Default::default() };
        assert!(bad.validate().unwrap_err().contains("at least the hold time"));
    }

    #[test]
    fn a_lost_client_makes_its_copter_hover_or_go_back_to_its_scene_command() {
        let (_, world) = sim_core::scene::load_default();
        let state = world.initial_state();
        let scene_cmd = world.copters[0].initial_command.clone();
        for action in [ClientLostAction::Hover, ClientLostAction::Scene, ClientLostAction::Land] {
            let mut inputs = world.initial_inputs();
            let flying = &mut inputs.commands[0];
            (flying.pitch_rad, flying.height_m, flying.velocity_m_s) = (0.1, 1.7, Some([0.4, 0.0]));
            let commanded = inputs.commands[0].clone();
            let mut fs = Failsafe::new(FailsafeOptions { client_lost: action, ..Default::default() });
            let mut ev = Vec::new();
            fs.client_lost(&world, &state, 0, "pilot", &mut inputs, &mut ev);
            assert_eq!(ev[0].kind, FailsafeKind::ClientLost { client: "pilot".into(), action });
            let cmd = &inputs.commands[0];
            match action {
                ClientLostAction::Hover => {
                    // Level, no cruise, holding the height it has now (on the floor: staying
                    // there, motors off).
                    assert_eq!((cmd.pitch_rad, cmd.velocity_m_s), (0.0, None));
                    assert!(state.pose(0).pos_m.z < 0.05);
                    assert_eq!((cmd.height_m, cmd.throttle), (0.0, 0.0));
                    assert!(fs.active(0) && ev.len() == 1);
                }
                ClientLostAction::Scene => {
                    assert_eq!(*cmd, scene_cmd);
                    assert!(!fs.active(0), "nothing to undo: the scene's command is the copter's own");
                }
                ClientLostAction::Land => {
                    assert!(matches!(ev[1].kind, FailsafeKind::Land { .. }));
                }
            }
            // A new controller's command ends it, restoring what was flown before.
            if fs.active(0) {
                fs.commanded(0, &mut inputs, &mut ev);
                assert!(matches!(ev.last().unwrap().kind, FailsafeKind::Resumed { .. }));
                assert_eq!(inputs.commands[0], commanded);
            }
        }
    }

    #[test]
    fn the_hold_time_follows_the_aircrafts_own_telemetry_period() {
        let (_, world) = sim_core::scene::load_default();
        let state = world.initial_state();
        let mut inputs = world.initial_inputs();
        let mut fs = Failsafe::new(FailsafeOptions::default());
        let t0 = Instant::now();
        let ms = |m: u64| t0 + Duration::from_millis(m);
        let mut ev = Vec::new();
        // An NPS rotorcraft's default telemetry: ROTORCRAFT_FP every 250 ms.
        for k in 0..20 {
            fs.telemetry(0, ms(250 * k), &mut inputs, &mut ev);
        }
        assert!((fs.hold_after_s(0) - 1.0).abs() < 1e-9, "{}", fs.hold_after_s(0));
        // A 560 ms gap (its p99) is not a lost link.
        fs.after_step(&world, &state, &mut inputs, ms(250 * 19 + 560), &mut ev);
        assert!(ev.is_empty(), "{ev:?}");
        fs.after_step(&world, &state, &mut inputs, ms(250 * 19 + 1100), &mut ev);
        assert!(matches!(ev[0].kind, FailsafeKind::Hold { .. }), "{ev:?}");
        // A FINken's 22 ms telemetry keeps the 0.5 s floor.
        let mut fast = Failsafe::new(FailsafeOptions::default());
        for k in 0..40 {
            fast.telemetry(1, ms(22 * k), &mut inputs, &mut ev);
        }
        assert_eq!(fast.hold_after_s(1), 0.5);
    }

    #[test]
    fn an_undriven_twin_has_no_failsafe_and_a_silent_one_holds_then_lands() {
        let (_, world) = sim_core::scene::load_default();
        let state = world.initial_state();
        let mut inputs = world.initial_inputs();
        let opts = FailsafeOptions { hold_after_s: 0.5, land_after_s: 1.0, ..Default::default() };
        let mut fs = Failsafe::new(opts);
        let t0 = Instant::now();
        let mut ev = Vec::new();
        fs.after_step(&world, &state, &mut inputs, t0 + Duration::from_secs(9), &mut ev);
        assert!(ev.is_empty(), "never driven: {ev:?}");
        fs.telemetry(0, t0, &mut inputs, &mut ev);
        fs.after_step(&world, &state, &mut inputs, t0 + Duration::from_millis(400), &mut ev);
        assert!(ev.is_empty());
        fs.after_step(&world, &state, &mut inputs, t0 + Duration::from_millis(600), &mut ev);
        assert_eq!(ev.len(), 1);
        assert!(matches!(ev[0].kind, FailsafeKind::Hold { .. }));
        fs.after_step(&world, &state, &mut inputs, t0 + Duration::from_millis(1100), &mut ev);
        assert!(matches!(ev[1].kind, FailsafeKind::Land { .. }), "{ev:?}");
        let before = inputs.commands[0].clone();
        fs.telemetry(0, t0 + Duration::from_millis(1200), &mut inputs, &mut ev);
        assert!(matches!(ev[2].kind, FailsafeKind::Resumed { silent_s } if (silent_s - 1.2).abs() < 1e-6));
        assert!(!fs.active(0));
        assert_ne!(before, inputs.commands[0], "the command from before the failsafe is back");
        assert_eq!(fs.counts.get("hold"), Some(&1));
    }
}

//! The loop side of mixed reality: [`Outbox`] runs inside the step loop (it needs the state):
//! after each step it produces the Paparazzi texts to send, on the **simulated** clock:
//! `VIRTUAL_SONAR` (or `SONAR_UPLINK`: the uplink each aircraft's messages.xml defines) for
//! every twin (at the sonar rate, or a configured period), and each virtual copter's telemetry
//! at the periods of its [`TelemetryPlan`]. Periods shorter than the control step give one
//! message per control step (the values change only that often).

use std::collections::BTreeMap;
use std::sync::Arc;

use sim_core::mixed::VirtualSonar;
use sim_core::{CopterKind, State, World};

use crate::ids::AcId;
use crate::mixed::plan::TelemetryPlan;
use crate::paparazzi::convert::{TelemetrySource, Uplink, telemetry_text, uplink_text};
use crate::paparazzi::messages::MessageSet;
use crate::wire::{sensors_msg, state_msg};

/// How the loop side sends Paparazzi messages.
#[derive(Clone, Debug)]
pub struct OutboxOptions {
    /// Key-expression prefix.
    pub prefix: String,
    /// Message definitions (the project's `messages.xml`).
    pub messages: Arc<MessageSet>,
    /// What virtual copters send.
    pub plan: TelemetryPlan,
    /// Period of the virtual-sonar uplink per twin, s; 0: at every sonar update.
    pub virtual_sonar_period_s: f64,
    /// Per aircraft, the uplink its firmware understands, where it is not the one `messages`
    /// defines ([`Uplink::defined_by`]).
    pub uplinks: BTreeMap<AcId, Uplink>,
}

impl OutboxOptions {
    /// The uplink aircraft `ac_id`'s twin sends: its own setting, else the one `messages`
    /// defines. An uplink `messages` does not define is never sent (it could not be encoded,
    /// and Paparazzi's `link` would drop it).
    pub fn uplink_for(&self, ac_id: AcId) -> Uplink {
        let defined = |u: Uplink| u.message().is_some_and(|m| self.messages.by_class_and_name("datalink", m).is_some());
        match self.uplinks.get(&ac_id) {
            Some(&u) if u == Uplink::None || defined(u) => u,
            Some(_) => Uplink::None,
            None => Uplink::defined_by(&self.messages),
        }
    }

    /// One line per twin (or copter flown by an outside autopilot) of `world` for the start of
    /// a run: the uplink it gets, or that it gets none and why.
    pub fn uplink_lines(&self, world: &World) -> Vec<String> {
        world
            .copters
            .iter()
            .filter(|c| c.kind.is_real_layer())
            .filter_map(|c| {
                let ac = c.ac_id?;
                Some(match (self.uplink_for(ac), self.uplinks.get(&ac)) {
                    (Uplink::None, Some(Uplink::None)) => {
                        format!("{} (aircraft {ac}): no virtual-sonar uplink (set so)", c.name)
                    }
                    (Uplink::None, Some(u)) => format!(
                        "{} (aircraft {ac}): no virtual-sonar uplink: {} is not a datalink message of {}",
                        c.name,
                        u.message().unwrap_or("-"),
                        self.messages.source
                    ),
                    (Uplink::None, None) => format!(
                        "{} (aircraft {ac}): no virtual-sonar uplink: {} defines neither SONAR_UPLINK nor VIRTUAL_SONAR",
                        c.name, self.messages.source
                    ),
                    (u, _) => format!(
                        "{} (aircraft {ac}): virtual sonar as {} from `{}`",
                        c.name,
                        u.message().unwrap_or("-"),
                        u.sender()
                    ),
                })
            })
            .collect()
    }
}

/// A Paparazzi text to publish.
#[derive(Clone, Debug, PartialEq)]
pub struct PprzOut {
    /// Its key (`<prefix>/pprz/<sender>/<NAME>`).
    pub key: String,
    /// The Ivy text.
    pub text: String,
    /// The aircraft a virtual-sonar uplink is for (`None`: a virtual copter's telemetry): the
    /// step loop counts an autopilot aircraft's uplink (`crate::autopilot`).
    pub uplink_to: Option<AcId>,
}

/// The loop side of mixed reality (see the module docs).
#[derive(Debug)]
pub struct Outbox {
    opts: OutboxOptions,
    /// Per copter: next due time of each plan message (virtual copters) or of
    /// `VIRTUAL_SONAR` (twins), s.
    due: Vec<Vec<f64>>,
    virtual_sonar: VirtualSonar,
    /// Messages whose encoding failed, by name (reported once each).
    failed: BTreeMap<String, u64>,
    /// Plan messages the simulator cannot produce (reported once each).
    unsupported: Vec<String>,
}

impl Outbox {
    /// An outbox for `world`.
    pub fn new(opts: OutboxOptions) -> Self {
        let unsupported: Vec<String> = opts
            .plan
            .periods
            .iter()
            .filter(|(n, _)| !crate::paparazzi::convert::TELEMETRY_MESSAGES.contains(&n.as_str()))
            .map(|(n, _)| n.clone())
            .collect();
        if !unsupported.is_empty() {
            tracing::warn!(
                "telemetry plan {}: virtual copters cannot send {} (not modelled)",
                opts.plan.label,
                unsupported.join(", ")
            );
        }
        Self { opts, due: Vec::new(), virtual_sonar: VirtualSonar::default(), failed: BTreeMap::new(), unsupported }
    }

    /// Encoding failures by message name.
    pub fn failures(&self) -> &BTreeMap<String, u64> {
        &self.failed
    }

    /// Appends what is due after the step that led to `state` to `out`. `sonar_updated`:
    /// whether this step sampled the sonars.
    pub fn after_step(
        &mut self,
        world: &World,
        state: &State,
        inputs: &sim_core::Inputs,
        sonar_updated: bool,
        out: &mut Vec<PprzOut>,
    ) {
        let t = state.time_s(world);
        let n = world.copters.len();
        while self.due.len() < n {
            let i = self.due.len();
            let slots = match world.copters[i].kind {
                CopterKind::Real | CopterKind::Autopilot => 1,
                CopterKind::Virtual => self.opts.plan.periods.len(),
            };
            self.due.push(vec![t; slots]);
        }
        let dt = world.params.control_dt_s;
        // Fires at most once per step, and keeps the schedule on its grid.
        let fire = |due: &mut f64, period: f64| -> bool {
            if t + 1e-9 < *due {
                return false;
            }
            let period = period.max(1e-6);
            while *due <= t + 1e-9 {
                *due += period;
            }
            true
        };
        let mut prepared = false;
        for i in 0..n {
            let def = &world.copters[i];
            let Some(ac_id) = def.ac_id else { continue };
            match def.kind {
                // A real copter and one flown by an outside autopilot get the virtual sonar;
                // the latter's telemetry is its autopilot's own.
                CopterKind::Real | CopterKind::Autopilot => {
                    if !sonar_updated {
                        continue;
                    }
                    let period = self.opts.virtual_sonar_period_s.max(dt * 0.5);
                    if !fire(&mut self.due[i][0], period) {
                        continue;
                    }
                    if !prepared {
                        self.virtual_sonar.prepare(world, state);
                        prepared = true;
                    }
                    let uplink = self.opts.uplink_for(ac_id);
                    let Some(name) = uplink.message() else { continue };
                    let readings = self.virtual_sonar.readings(world, state, i);
                    match uplink_text(&self.opts.messages, uplink, ac_id, readings) {
                        Ok(Some(text)) => {
                            out.push(PprzOut { key: self.key(uplink.sender(), name), text, uplink_to: Some(ac_id) })
                        }
                        Ok(None) => {}
                        Err(e) => self.fail(name, &e.to_string()),
                    }
                }
                CopterKind::Virtual => {
                    let mut src = None;
                    for k in 0..self.opts.plan.periods.len() {
                        let (name, period) = &self.opts.plan.periods[k];
                        if self.unsupported.contains(name) || !fire(&mut self.due[i][k], *period) {
                            continue;
                        }
                        let (st, se) = src
                            .get_or_insert_with(|| (state_msg(world, state, inputs, i), sensors_msg(world, state, i)));
                        let source = TelemetrySource { state: st, sensors: se, setpoint: state.copters[i].setpoint };
                        match telemetry_text(&self.opts.messages, ac_id, name, &source) {
                            Some(Ok(text)) => {
                                out.push(PprzOut { key: self.key(&ac_id.to_string(), name), text, uplink_to: None })
                            }
                            Some(Err(e)) => {
                                let name = name.clone();
                                self.fail(&name, &e.to_string());
                            }
                            None => {}
                        }
                    }
                }
            }
        }
    }

    fn key(&self, sender: &str, name: &str) -> String {
        format!("{}/pprz/{sender}/{name}", self.opts.prefix)
    }

    fn fail(&mut self, name: &str, why: &str) {
        let n = self.failed.entry(name.to_owned()).or_insert(0);
        if *n == 0 {
            tracing::warn!("cannot encode {name}: {why}");
        }
        *n += 1;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_virtual_copter_registers_with_the_server_before_it_reports_positions() {
        // Paparazzi's server registers an aircraft on ALIVE and converts ROTORCRAFT_FP into a
        // position only once INS_REF has given the origin: both must precede the first
        // ROTORCRAFT_FP.
        let (_, world) = sim_core::scene::load_default();
        let mut state = world.initial_state();
        let inputs = world.initial_inputs();
        let messages = Arc::new(crate::paparazzi::convert::project_messages());
        let mut outbox = Outbox::new(OutboxOptions {
            prefix: "t".into(),
            messages: messages.clone(),
            plan: TelemetryPlan::project_default(),
            virtual_sonar_period_s: 0.0,
            uplinks: Default::default(),
        });
        let mut out = Vec::new();
        for _ in 0..3 {
            sim_core::step(&world, &mut state, &inputs);
            outbox.after_step(&world, &state, &inputs, true, &mut out);
        }
        let ac = world.copters[0].ac_id.unwrap();
        let names: Vec<&str> = out
            .iter()
            .filter(|o| o.text.starts_with(&format!("{ac} ")))
            .map(|o| o.text.split(' ').nth(1).unwrap())
            .collect();
        let pos = |n: &str| names.iter().position(|x| *x == n).unwrap_or_else(|| panic!("no {n} in {names:?}"));
        assert!(pos("ALIVE") < pos("ROTORCRAFT_FP") && pos("INS_REF") < pos("ROTORCRAFT_FP"), "{names:?}");
        let alive = out.iter().find(|o| o.text.starts_with(&format!("{ac} ALIVE"))).unwrap();
        assert_eq!(alive.text, format!("{ac} ALIVE 0,0,0,0,0,0,0,0,0,0,0,0,0,0,0,0"));
        for o in &out {
            messages.decode(&o.text).unwrap_or_else(|e| panic!("{}: {e}", o.text));
        }
        assert!(outbox.failures().is_empty(), "{:?}", outbox.failures());
    }
}

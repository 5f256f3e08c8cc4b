//! Run summaries and derived-model reports, as text and JSON.

use std::fmt::Write as _;

use serde::Serialize;
use sim_core::world::CopterDef;
use sim_core::{Event, State, StepReport, World};

/// After take-off, height errors count from this many seconds on (the climb is not an error).
const HEIGHT_SETTLE_S: f64 = 5.0;

/// Follows a run to build its summary.
#[derive(Debug)]
pub struct Tracker {
    worst_height_error_m: Vec<f32>,
    crashes: Vec<CrashLine>,
}

#[derive(Clone, Debug, Serialize)]
pub struct CrashLine {
    copter: String,
    time_s: f64,
    cause: sim_core::CrashCause,
}

impl Tracker {
    pub fn new(world: &World) -> Self {
        Self { worst_height_error_m: vec![0.0; world.copters.len()], crashes: Vec::new() }
    }

    pub fn observe(&mut self, world: &World, state: &State, report: &StepReport) {
        // Copters spawned at runtime join the summary.
        self.worst_height_error_m.resize(world.copters.len(), 0.0);
        for e in &report.events {
            if let Event::Crashed { copter, cause } = e {
                self.crashes.push(CrashLine {
                    copter: world.copters[*copter].name.clone(),
                    time_s: state.time_s(world),
                    cause: *cause,
                });
            }
        }
        let t = state.time_s(world);
        for (i, c) in state.copters.iter().enumerate() {
            let Some(took_off) = c.took_off_tick else { continue };
            if c.crash.is_some() || c.setpoint.height_m <= 0.0 || t < world.time_at(took_off) + HEIGHT_SETTLE_S {
                continue;
            }
            let err = (state.pose(i).pos_m.z - c.setpoint.height_m).abs();
            self.worst_height_error_m[i] = self.worst_height_error_m[i].max(err);
        }
    }

    /// The run's summary; `spent` is its wall time and this process's CPU time over it, s.
    pub fn summary(
        &self,
        world: &World,
        state: &State,
        scene: &str,
        spent: (f64, Option<f64>),
        stepped: u64,
        overruns: u64,
    ) -> Summary {
        let (wall_s, cpu_s) = spent;
        let sim_s = state.time_s(world);
        // A resumed run flew from its checkpoint on, not from 0.
        let flown_s = stepped as f64 * world.params.control_dt_s;
        // A shard reports its own copters only.
        let copters: Vec<CopterLine> = world
            .copters
            .iter()
            .enumerate()
            .filter(|&(i, _)| state.owns(i))
            .map(|(i, c)| {
                let p = state.pose(i);
                CopterLine {
                    id: i,
                    digest: crate::shardcmd::copter_digest(&state.copters[i]),
                    name: c.name.clone(),
                    kind: c.kind,
                    final_pos_m: [p.pos_m.x, p.pos_m.y, p.pos_m.z],
                    final_yaw_deg: p.rpy_rad[2].to_degrees(),
                    crashed: state.copters[i].crash.is_some(),
                    worst_height_error_m: (state.copters[i].took_off_tick.is_some())
                        .then_some(self.worst_height_error_m[i]),
                }
            })
            .collect();
        Summary {
            scene: scene.to_owned(),
            world: world.name.clone(),
            seed: world.params.seed,
            copters_count: copters.len(),
            sim_time_s: sim_s,
            flown_s,
            wall_time_s: wall_s,
            cpu_s,
            cpu_per_sim_s: cpu_s.filter(|_| flown_s > 0.0).map(|c| c / flown_s),
            real_time_factor: if wall_s > 0.0 { flown_s / wall_s } else { f64::INFINITY },
            control_steps: state.tick,
            realtime_overruns: overruns,
            crashes: self.crashes.clone(),
            copters,
        }
    }
}

#[derive(Debug, Serialize)]
pub struct CopterLine {
    id: usize,
    name: String,
    /// Its bits at the end (see `shardcmd::copter_digest`): equal runs, equal digests.
    digest: String,
    kind: sim_core::CopterKind,
    final_pos_m: [f32; 3],
    final_yaw_deg: f32,
    crashed: bool,
    /// Largest |z − height target| from 5 s after take-off on; `None` if it never flew.
    worst_height_error_m: Option<f32>,
}

/// What `twinswarm run` prints.
#[derive(Debug, Serialize)]
pub struct Summary {
    scene: String,
    world: String,
    seed: u64,
    copters_count: usize,
    /// The simulated time at the end, s.
    sim_time_s: f64,
    /// The simulated time this process stepped, s: `sim_time_s` less where a resumed run's
    /// checkpoint began.
    flown_s: f64,
    wall_time_s: f64,
    /// This process's CPU time over the same span, all its threads (the simulation's and the
    /// transport's), s.
    cpu_s: Option<f64>,
    /// `cpu_s` per simulated second flown: the work of a simulated second, whatever the cores'
    /// waits (`cluster` reports the same for all its processes).
    cpu_per_sim_s: Option<f64>,
    /// `flown_s / wall_time_s`.
    real_time_factor: f64,
    control_steps: u64,
    realtime_overruns: u64,
    crashes: Vec<CrashLine>,
    copters: Vec<CopterLine>,
}

impl Summary {
    pub fn to_text(&self) -> String {
        let mut s = String::new();
        let _ = writeln!(s, "twinswarm run: {} (world {:?}, seed {})", self.scene, self.world, self.seed);
        let _ = writeln!(
            s,
            "  {} copters, {:.1} s simulated{} in {:.3} s wall ({:.2}x real time, {} control steps{})",
            self.copters_count,
            self.flown_s,
            match self.sim_time_s - self.flown_s {
                from if from > 1e-9 => format!(" (resumed at {from:.1} s)"),
                _ => String::new(),
            },
            self.wall_time_s,
            self.real_time_factor,
            self.control_steps,
            if self.realtime_overruns > 0 {
                format!(", {} real-time overruns", self.realtime_overruns)
            } else {
                String::new()
            }
        );
        if self.copters.len() > PER_COPTER_ROWS_UP_TO {
            self.aggregate_text(&mut s);
            return s;
        }
        if self.crashes.is_empty() {
            let _ = writeln!(s, "  crashes: none");
        } else {
            let _ = writeln!(s, "  crashes: {}", self.crashes.len());
            for c in &self.crashes {
                let _ = writeln!(s, "    {} at {:.2} s: {:?}", c.copter, c.time_s, c.cause);
            }
        }
        let _ = writeln!(
            s,
            "  {:<12} {:<8} {:>24} {:>9} {:>18}",
            "copter", "kind", "final position (m)", "yaw (°)", "worst |dz| (cm)"
        );
        for c in &self.copters {
            let _ = writeln!(
                s,
                "  {:<12} {:<8} {:>24} {:>9.1} {:>18}{}",
                c.name,
                format!("{:?}", c.kind).to_lowercase(),
                format!("({:.2}, {:.2}, {:.2})", c.final_pos_m[0], c.final_pos_m[1], c.final_pos_m[2]),
                c.final_yaw_deg,
                c.worst_height_error_m.map_or("-".into(), |e| format!("{:.2}", e * 100.0)),
                if c.crashed { "  CRASHED" } else { "" }
            );
        }
        s
    }
}

/// Up to this many copters the text summary has a row per copter; above, aggregates (the
/// per-copter detail is in `--json` and the log).
const PER_COPTER_ROWS_UP_TO: usize = 20;

/// How many of the first crashes and of the worst height holds a large swarm's summary lists.
const WORST_FEW: usize = 5;

/// A crash cause's kind, for counting.
fn cause_kind(c: &sim_core::CrashCause) -> &'static str {
    use sim_core::CrashCause as C;
    match c {
        C::Wall => "wall",
        C::Ceiling => "ceiling",
        C::Box { .. } => "box",
        C::Floor { .. } => "floor",
        C::Copter { .. } => "copter",
        C::Tilt { .. } => "tilt",
    }
}

/// The `q` quantile of sorted values (nearest rank).
fn quantile(sorted: &[f32], q: f64) -> f32 {
    let i = ((sorted.len() as f64 - 1.0) * q).round() as usize;
    sorted[i.min(sorted.len() - 1)]
}

impl Summary {
    /// The summary of a swarm too large for a row per copter: counts, crashes by cause with
    /// their timing and the first few, height-hold percentiles and the worst few.
    fn aggregate_text(&self, s: &mut String) {
        let crashed = self.copters.iter().filter(|c| c.crashed).count();
        let flew = self.copters.iter().filter(|c| c.worst_height_error_m.is_some()).count();
        let _ = writeln!(
            s,
            "  copters: {} flew, {} crashed, {} flying or landed at the end (a row per copter: --json, or the log)",
            flew,
            crashed,
            self.copters.len() - crashed
        );
        if self.crashes.is_empty() {
            let _ = writeln!(s, "  crashes: none");
        } else {
            let mut by_cause: std::collections::BTreeMap<&str, usize> = std::collections::BTreeMap::new();
            for c in &self.crashes {
                *by_cause.entry(cause_kind(&c.cause)).or_default() += 1;
            }
            let causes: Vec<String> = by_cause.iter().map(|(k, n)| format!("{k} {n}")).collect();
            let mut times: Vec<f32> = self.crashes.iter().map(|c| c.time_s as f32).collect();
            times.sort_by(f32::total_cmp);
            let _ = writeln!(
                s,
                "  crashes: {} ({}); times: first {:.2} s, median {:.2} s, last {:.2} s",
                self.crashes.len(),
                causes.join(", "),
                times[0],
                quantile(&times, 0.5),
                times[times.len() - 1]
            );
            for c in self.crashes.iter().take(WORST_FEW) {
                let _ = writeln!(s, "    {} at {:.2} s: {:?}", c.copter, c.time_s, c.cause);
            }
            if self.crashes.len() > WORST_FEW {
                let _ = writeln!(s, "    … and {} more", self.crashes.len() - WORST_FEW);
            }
        }
        let mut held: Vec<(&str, f32)> = self
            .copters
            .iter()
            .filter(|c| !c.crashed)
            .filter_map(|c| Some((c.name.as_str(), c.worst_height_error_m?)))
            .collect();
        if held.is_empty() {
            return;
        }
        held.sort_by(|a, b| b.1.total_cmp(&a.1));
        let mut errs: Vec<f32> = held.iter().map(|h| h.1 * 100.0).collect();
        errs.sort_by(f32::total_cmp);
        let _ = writeln!(
            s,
            "  worst |dz| of the {} that did not crash (cm): median {:.2}, p95 {:.2}, max {:.2}; worst: {}",
            held.len(),
            quantile(&errs, 0.5),
            quantile(&errs, 0.95),
            errs[errs.len() - 1],
            held.iter().take(WORST_FEW).map(|(n, e)| format!("{n} {:.2}", e * 100.0)).collect::<Vec<_>>().join(", ")
        );
    }
}

/// `twinswarm inspect`: the derived model of one copter.
#[derive(Debug, Serialize)]
pub struct CopterModel {
    copter: String,
    mass_kg: f32,
    inertia_kg_m2: [f32; 3],
    hover_thrust_per_rotor_n: f32,
    disc_area_m2: f32,
    v_rotor_m_s: f32,
    v_final_m_s: f32,
    mass_flow_kg_s: f32,
    particle_mass_kg: f32,
    particle_density_kg_m3: f32,
    particle_rate_per_v_final_per_m: f32,
    particle_rate_hover_hz: f32,
    particles_per_physics_step: f32,
    k_n_s2: f32,
    d_n_m_s2: f32,
    omega_hover_rad_s: f32,
    max_thrust_per_rotor_n: f32,
}

impl CopterModel {
    pub fn new(world: &World, c: &CopterDef) -> Self {
        let af = &world.airframes[c.airframe];
        Self {
            copter: c.name.clone(),
            mass_kg: af.mass_kg,
            inertia_kg_m2: af.inertia_kg_m2,
            hover_thrust_per_rotor_n: af.hover_thrust_per_rotor_n,
            disc_area_m2: af.disc_area_m2,
            v_rotor_m_s: af.v_rotor_m_s,
            v_final_m_s: af.v_final_m_s,
            mass_flow_kg_s: af.mass_flow_kg_s,
            particle_mass_kg: af.particle_mass_kg,
            particle_density_kg_m3: af.particle_density_kg_m3,
            particle_rate_per_v_final_per_m: af.particle_rate_per_v_final_per_m,
            particle_rate_hover_hz: af.spec.particle_rate_hover_hz,
            particles_per_physics_step: af.spec.particle_rate_hover_hz * world.params.physics_dt_s as f32,
            k_n_s2: af.k_n_s2,
            d_n_m_s2: af.d_n_m_s2,
            omega_hover_rad_s: af.omega_hover_rad_s,
            max_thrust_per_rotor_n: af.max_thrust_per_rotor_n,
        }
    }

    pub fn to_text(&self) -> String {
        let mut s = String::new();
        let _ = writeln!(s, "copter {}", self.copter);
        let rows: [(&str, String, &str); 17] = [
            ("mass", format!("{:.4}", self.mass_kg), "kg"),
            (
                "inertia (xx, yy, zz)",
                format!("{:.3e}, {:.3e}, {:.3e}", self.inertia_kg_m2[0], self.inertia_kg_m2[1], self.inertia_kg_m2[2]),
                "kg m²",
            ),
            ("hover thrust per rotor F = m g / 4", format!("{:.5}", self.hover_thrust_per_rotor_n), "N"),
            ("rotor disc area A", format!("{:.6}", self.disc_area_m2), "m²"),
            ("v_rotor = sqrt(F / (2 rho A))", format!("{:.4}", self.v_rotor_m_s), "m/s"),
            ("v_final = 2 v_rotor", format!("{:.4}", self.v_final_m_s), "m/s"),
            ("mass flow m' = F / v_final", format!("{:.5}", self.mass_flow_kg_s), "kg/s"),
            ("particle mass m_px = m' / n'", format!("{:.5e}", self.particle_mass_kg), "kg"),
            ("particle density rho_px", format!("{:.2}", self.particle_density_kg_m3), "kg/m³"),
            ("n' / v_final = rho A / (2 m_px)", format!("{:.4}", self.particle_rate_per_v_final_per_m), "1/m"),
            ("particle rate at hover n'", format!("{:.1}", self.particle_rate_hover_hz), "1/s"),
            ("particles per physics step at hover", format!("{:.3}", self.particles_per_physics_step), ""),
            ("thrust coefficient k", format!("{:.4e}", self.k_n_s2), "N s²"),
            ("drag-torque coefficient d", format!("{:.4e}", self.d_n_m_s2), "N m s²"),
            ("rotor speed at hover", format!("{:.1}", self.omega_hover_rad_s), "rad/s"),
            ("max thrust per rotor", format!("{:.4}", self.max_thrust_per_rotor_n), "N"),
            ("", String::new(), ""),
        ];
        for (name, v, unit) in rows.iter().filter(|r| !r.0.is_empty()) {
            let _ = writeln!(s, "  {name:<38} {v:>30} {unit}");
        }
        s
    }
}

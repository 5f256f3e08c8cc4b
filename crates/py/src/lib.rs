//! `twinswarm._native`: the simulator as a Python extension, on the CLI's engine
//! ([`bridge::engine::flight::Flight`]). The Python half (`python/twinswarm/__init__.py`) checks
//! arguments, shapes arrays and wraps these calls; what it hands over here is already typed.
//!
//! Observations leave as one `bytearray` of little-endian `f32`, row-major (copter, column),
//! that numpy views without a Python object per copter. Actions arrive the same way, as
//! `f64`. Every command goes through the bus's own validation and `apply`
//! ([`bridge::wire::CommandMsg`]), so a Python run and a Zenoh controller sending the same
//! numbers fly the same bits.

use std::path::PathBuf;
use std::sync::{Arc, Mutex, MutexGuard};

use bridge::engine::LoopOptions;
use bridge::engine::flight::{Flight, Halt, Recorder};
use bridge::live::LiveServer;
use bridge::log::{LogMeta, LogOptions, Logger};
use bridge::wire::CommandMsg;
use pyo3::exceptions::{PyRuntimeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::{PyByteArray, PyBytes};
use rayon::prelude::*;
use sim_core::scene::{self, SceneSpec};
use sim_core::{CopterKind, FlightMode, Inputs, State, World};

/// Columns of `truth()`.
const TRUTH_COLUMNS: usize = 14;
/// Columns of `sensors()`.
const SENSOR_COLUMNS: usize = 17;

/// One simulated swarm (see the Python `twinswarm.Sim`).
#[pyclass(module = "twinswarm._native", name = "Sim")]
#[derive(Debug)]
struct Sim {
    /// Behind a mutex only because a Python class must be `Sync`; methods that step hold
    /// `&mut self` and reach it without locking.
    flight: Mutex<Flight>,
    spec: SceneSpec,
    origin: String,
    /// The scene's TOML as given (the embedded lab's file for `None`).
    text: String,
    /// The live view's runtime and server, while it serves.
    live: Option<(tokio::runtime::Runtime, Arc<LiveServer>)>,
    /// Whether a log file or the live view records this Sim (it cannot be reset then).
    recording: bool,
}

fn bad(msg: impl Into<String>) -> PyErr {
    PyValueError::new_err(msg.into())
}

/// The scene: a file, TOML text, or the embedded lab.
fn load_spec(path: Option<&str>, text: Option<&str>) -> PyResult<(String, String, SceneSpec)> {
    let (origin, toml) = match (path, text) {
        (Some(p), _) => {
            let t = std::fs::read_to_string(p).map_err(|e| bad(format!("scene: cannot read {p:?}: {e}")))?;
            (p.to_owned(), t)
        }
        (None, Some(t)) => ("<scene text>".to_owned(), t.to_owned()),
        (None, None) => (scene::DEFAULT_SCENE_ORIGIN.to_owned(), scene::DEFAULT_SCENE_TOML.to_owned()),
    };
    let (spec, _) = scene::load(&origin, &toml).map_err(|e| bad(format!("scene: {e}")))?;
    Ok((origin, toml, spec))
}

fn compile(spec: &SceneSpec) -> PyResult<World> {
    scene::compile(spec).map_err(|e| bad(format!("scene: {e}")))
}

/// The log file (with the live view fed from its writer), or the live view alone.
fn start_recorder(
    world: &World,
    scene_text: &str,
    origin: &str,
    log: Option<PathBuf>,
    live: Option<Arc<LiveServer>>,
) -> PyResult<Recorder> {
    let options = LogOptions { live: live.clone(), ..Default::default() };
    let logger = match (log, live) {
        (None, None) => None,
        (None, Some(live)) => Some(
            Logger::live_only(world, live, LogOptions::default())
                .map_err(|e| PyRuntimeError::new_err(format!("live view: {e}")))?,
        ),
        (Some(path), _) => {
            if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
                std::fs::create_dir_all(dir)
                    .map_err(|e| bad(format!("log: cannot create directory {}: {e}", dir.display())))?;
            }
            let meta = LogMeta {
                command_line: format!("python: twinswarm.Sim(scene={origin:?})"),
                scene_origin: origin.to_owned(),
                epoch_ns: None,
            };
            Some(
                Logger::with_options(&path, world, scene_text, meta, options)
                    .map_err(|e| bad(format!("log: cannot write {}: {e}", path.display())))?,
            )
        }
    };
    // A log error stops the Sim (its next `step` raises it), as `run --on-log-error stop` does.
    let stop = logger.is_some().then(|| Arc::new(std::sync::atomic::AtomicBool::new(false)));
    Ok(Recorder::new(logger, stop))
}

fn new_flight(world: World, recorder: Recorder) -> Flight {
    let (state, inputs) = (world.initial_state(), world.initial_inputs());
    Flight::new(world, state, inputs, &LoopOptions::default(), recorder, ())
}

impl Sim {
    fn flight(&self) -> MutexGuard<'_, Flight> {
        bridge::lock(&self.flight)
    }

    fn flight_mut(&mut self) -> &mut Flight {
        self.flight.get_mut().unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    fn world(&self) -> Arc<World> {
        self.flight().world().clone()
    }

    fn step_n(&mut self, steps: u64) -> Result<(), String> {
        let flight = self.flight_mut();
        for _ in 0..steps {
            match flight.step() {
                Ok(_) => {}
                Err(Halt::Log) => {
                    let e = flight.recorder.error().map(|(t, e)| format!("at control step {t}: {e}"));
                    return Err(format!("logging failed {}", e.unwrap_or_default()));
                }
                Err(Halt::Shard(e) | Halt::Checkpoint(e)) => return Err(e),
                Err(Halt::Stopped) => return Err("stopped while waiting for its shard's neighbours".into()),
            }
        }
        Ok(())
    }

    /// Finishes the log and stops the live view.
    fn finish(&mut self) -> Result<(), String> {
        let recorder = std::mem::take(&mut self.flight_mut().recorder);
        let (log, error) = recorder.into_parts();
        self.live = None;
        self.recording = false;
        if let Some(l) = log {
            l.finish().map_err(|e| format!("finishing the log: {e}"))?;
        }
        match error {
            Some((tick, e)) => Err(format!("logging failed at control step {tick}: {e}")),
            None => Ok(()),
        }
    }

    /// One validated command per row, all checked before any applies.
    fn commands(&self, kind: &str, rows: &[f64], cols: usize, ids: &[usize]) -> PyResult<Vec<CommandMsg>> {
        let world = &*self.world();
        let f = |v: f64| v as f32;
        ids.iter()
            .enumerate()
            .map(|(row, &id)| {
                let r = &rows[row * cols..(row + 1) * cols];
                let name = &world.copters[id].name;
                if world.copters[id].kind == CopterKind::Real {
                    return Err(bad(format!(
                        "command({kind:?}): copter {id} ({name:?}) is a twin: its real copter's telemetry drives it"
                    )));
                }
                let cmd = match kind {
                    "velocity" => CommandMsg {
                        mode: Some(FlightMode::Velocity),
                        velocity: Some([f(r[0]), f(r[1])]),
                        height: Some(f(r[2])),
                        yaw: Some(f(r[3])),
                        ..Default::default()
                    },
                    "target" => CommandMsg {
                        mode: Some(FlightMode::Target),
                        target: Some([f(r[0]), f(r[1]), f(r[2])]),
                        ..Default::default()
                    },
                    "attitude" => CommandMsg {
                        mode: Some(FlightMode::Manual),
                        roll: Some(f(r[0])),
                        pitch: Some(f(r[1])),
                        yaw: Some(f(r[2])),
                        throttle: Some(f(r[3])),
                        height: Some(0.0),
                        ..Default::default()
                    },
                    "rotors" => CommandMsg {
                        mode: Some(FlightMode::Rotors),
                        rotors: Some([f(r[0]), f(r[1]), f(r[2]), f(r[3])]),
                        ..Default::default()
                    },
                    other => return Err(bad(format!("unknown command kind {other:?}"))),
                };
                cmd.validate(world).map_err(|e| {
                    // The attitude kind's fourth column is `thrust` (the bus calls it throttle).
                    let e = match kind {
                        "attitude" => e.to_string().replace("`throttle`", "`thrust`"),
                        _ => e.to_string(),
                    };
                    bad(format!("command({kind:?}): row {row} (copter {id}, {name:?}): {e}"))
                })?;
                Ok(cmd)
            })
            .collect()
    }
}

#[pymethods]
impl Sim {
    #[new]
    #[pyo3(signature = (scene_path=None, scene_text=None, seed=None, threads=1, log=None, foxglove=None))]
    fn new(
        scene_path: Option<String>,
        scene_text: Option<String>,
        seed: Option<u64>,
        threads: usize,
        log: Option<PathBuf>,
        foxglove: Option<String>,
    ) -> PyResult<Self> {
        let (origin, text, mut spec) = load_spec(scene_path.as_deref(), scene_text.as_deref())?;
        if let Some(s) = seed {
            spec.sim.seed = s;
        }
        if !(1..=256).contains(&threads) {
            return Err(bad(format!("threads must be 1 to 256, got {threads}")));
        }
        spec.sim.threads = threads;
        let world = compile(&spec)?;
        let live = match foxglove {
            None => None,
            Some(a) => {
                let addr: std::net::SocketAddr = a
                    .parse()
                    .map_err(|e| bad(format!("foxglove: {a:?} is not an address like 127.0.0.1:8765: {e}")))?;
                let rt = tokio::runtime::Builder::new_multi_thread()
                    .worker_threads(1)
                    .enable_all()
                    .build()
                    .map_err(|e| PyRuntimeError::new_err(format!("foxglove: {e}")))?;
                let server = LiveServer::start(addr, "twinswarm", rt.handle())
                    .map_err(|e| bad(format!("foxglove: cannot listen on {addr}: {e}")))?;
                Some((rt, Arc::new(server)))
            }
        };
        let recording = log.is_some() || live.is_some();
        let recorder = start_recorder(&world, &text, &origin, log, live.as_ref().map(|l| l.1.clone()))?;
        Ok(Self { flight: Mutex::new(new_flight(world, recorder)), spec, origin, text, live, recording })
    }

    /// Back to tick 0, with a new seed if given.
    #[pyo3(signature = (seed=None))]
    fn reset(&mut self, seed: Option<u64>) -> PyResult<()> {
        if self.recording {
            return Err(PyRuntimeError::new_err(
                "a Sim that logs or serves the live view cannot be reset (its log's time would run backwards): make a new Sim",
            ));
        }
        if let Some(s) = seed {
            self.spec.sim.seed = s;
        }
        let world = compile(&self.spec)?;
        *self.flight_mut() = new_flight(world, Recorder::default());
        Ok(())
    }

    /// Runs `steps` control steps, without the GIL.
    #[pyo3(signature = (steps=1))]
    fn step(&mut self, py: Python<'_>, steps: u64) -> PyResult<()> {
        py.detach(|| self.step_n(steps)).map_err(PyRuntimeError::new_err)
    }

    /// Ground truth, `n × 14` little-endian f32 (see `TRUTH_COLUMNS`).
    fn truth<'py>(&self, py: Python<'py>) -> Bound<'py, PyByteArray> {
        let flight = self.flight();
        let state = flight.state();
        let mut out = Vec::with_capacity(state.copters.len() * TRUTH_COLUMNS * 4);
        for c in &state.copters {
            let m = &c.motion;
            let (p, v, q, w) = (m.pos_m, m.vel_m_s, m.rot, m.angvel_rad_s);
            let crashed = f32::from(u8::from(c.crash.is_some()));
            let row: [f32; TRUTH_COLUMNS] = [p.x, p.y, p.z, v.x, v.y, v.z, q.x, q.y, q.z, q.w, w.x, w.y, w.z, crashed];
            row.iter().for_each(|v| out.extend_from_slice(&v.to_le_bytes()));
        }
        PyByteArray::new(py, &out)
    }

    /// What the copters sense, `n × 17` little-endian f32 (see `SENSOR_COLUMNS`).
    fn sensors<'py>(&self, py: Python<'py>) -> Bound<'py, PyByteArray> {
        let flight = self.flight();
        let state = flight.state();
        let mut out = Vec::with_capacity(state.copters.len() * SENSOR_COLUMNS * 4);
        for c in &state.copters {
            let s = &c.sensors;
            let row: [f32; SENSOR_COLUMNS] = [
                s.sonar_m[0],
                s.sonar_m[1],
                s.sonar_m[2],
                s.sonar_m[3],
                s.ir_m.unwrap_or(f32::NAN),
                s.attitude_rad[0],
                s.attitude_rad[1],
                s.attitude_rad[2],
                s.rate_body_rad_s[0],
                s.rate_body_rad_s[1],
                s.rate_body_rad_s[2],
                s.accel_body_m_s2[0],
                s.accel_body_m_s2[1],
                s.accel_body_m_s2[2],
                s.height_est_m,
                s.battery_v,
                s.battery_charge,
            ];
            row.iter().for_each(|v| out.extend_from_slice(&v.to_le_bytes()));
        }
        PyByteArray::new(py, &out)
    }

    /// Commands of one kind for copters `ids`: `rows` holds `len(ids) × cols` little-endian
    /// f64. Nothing applies unless every row is valid.
    fn command(&mut self, kind: &str, rows: &[u8], cols: usize, ids: Vec<usize>) -> PyResult<()> {
        if rows.len() != ids.len() * cols * 8 {
            return Err(bad(format!("command({kind:?}): {} bytes for {} rows of {cols} f64", rows.len(), ids.len())));
        }
        let n = self.world().copters.len();
        if let Some(&id) = ids.iter().find(|&&id| id >= n) {
            return Err(bad(format!("command({kind:?}): no copter with id {id} (the swarm has {n})")));
        }
        let values: Vec<f64> =
            rows.chunks_exact(8).map(|b| f64::from_le_bytes(b.try_into().expect("8 bytes"))).collect();
        let cmds = self.commands(kind, &values, cols, &ids)?;
        let flight = self.flight_mut();
        for (cmd, &id) in cmds.iter().zip(&ids) {
            flight.command(id, cmd).map_err(|e| bad(format!("command({kind:?}): copter {id}: {e}")))?;
        }
        Ok(())
    }

    /// Flight modes by name for copters `ids`.
    fn command_mode(&mut self, modes: Vec<String>, ids: Vec<usize>) -> PyResult<()> {
        let world = self.world();
        let n = world.copters.len();
        let mut cmds = Vec::with_capacity(ids.len());
        if modes.len() != 1 && modes.len() != ids.len() {
            return Err(bad(format!("command('mode'): {} modes for {} copters", modes.len(), ids.len())));
        }
        let parse = |row: usize, mode: &String| -> PyResult<FlightMode> {
            serde_json::from_value(serde_json::Value::String(mode.clone())).map_err(|_| {
                bad(format!(
                    "command('mode'): row {row}: unknown mode {mode:?} (manual, mixed_manual, wall_avoid, target, velocity, rotors)"
                ))
            })
        };
        // One mode for every copter of `ids` is parsed once.
        let one = if modes.len() == 1 { Some(parse(0, &modes[0])?) } else { None };
        for (row, &id) in ids.iter().enumerate() {
            if id >= n {
                return Err(bad(format!("command('mode'): no copter with id {id} (the swarm has {n})")));
            }
            let parsed = match one {
                Some(mode) => mode,
                None => parse(row, &modes[row])?,
            };
            if self.world().copters[id].kind == CopterKind::Real {
                return Err(bad(format!(
                    "command('mode'): copter {id} is a twin: its real copter's telemetry drives it"
                )));
            }
            cmds.push(CommandMsg { mode: Some(parsed), ..Default::default() });
        }
        let flight = self.flight_mut();
        for (cmd, &id) in cmds.iter().zip(&ids) {
            flight.command(id, cmd).map_err(|e| bad(format!("command('mode'): copter {id}: {e}")))?;
        }
        Ok(())
    }

    /// The state and the commands, bit-exact (postcard).
    fn snapshot<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyBytes>> {
        let flight = self.flight();
        let snap = (flight.state(), flight.inputs());
        let bytes = postcard::to_allocvec(&snap).map_err(|e| PyRuntimeError::new_err(format!("snapshot: {e}")))?;
        Ok(PyBytes::new(py, &bytes))
    }

    /// Back to a snapshot of this scene.
    fn restore(&mut self, snap: &[u8]) -> PyResult<()> {
        if self.recording {
            return Err(PyRuntimeError::new_err(
                "a Sim that logs or serves the live view cannot restore a snapshot (its log's time would run backwards)",
            ));
        }
        let (state, inputs): (State, Inputs) =
            postcard::from_bytes(snap).map_err(|e| bad(format!("restore: not a snapshot of a Sim: {e}")))?;
        let n = self.world().copters.len();
        if state.copters.len() != n || inputs.commands.len() != n {
            return Err(bad(format!(
                "restore: the snapshot has {} copters, this Sim {n}: it is of another scene",
                state.copters.len()
            )));
        }
        self.flight_mut().restore(state, inputs);
        Ok(())
    }

    /// Each copter's digest, as `twinswarm run --json` prints it.
    fn digest(&self) -> Vec<String> {
        self.flight().state().copters.iter().map(|c| format!("{:016x}", c.digest())).collect()
    }

    /// Finishes the log and stops the live view; the Sim can still step, unrecorded.
    fn close(&mut self) -> PyResult<()> {
        self.finish().map_err(PyRuntimeError::new_err)
    }

    #[getter]
    fn n(&self) -> usize {
        self.world().copters.len()
    }

    #[getter]
    fn names(&self) -> Vec<String> {
        self.world().copters.iter().map(|c| c.name.clone()).collect()
    }

    #[getter]
    fn kinds(&self) -> Vec<&'static str> {
        self.world().copters.iter().map(|c| bridge::wire::kind_str(c.kind)).collect()
    }

    #[getter]
    fn tick(&self) -> u64 {
        self.flight().state().tick
    }

    #[getter]
    fn time_s(&self) -> f64 {
        let flight = self.flight();
        flight.state().time_s(flight.world())
    }

    #[getter]
    fn dt(&self) -> f64 {
        self.world().params.control_dt_s
    }

    #[getter]
    fn seed(&self) -> u64 {
        self.spec.sim.seed
    }

    #[getter]
    fn default_steps(&self) -> u64 {
        self.world().default_ticks()
    }

    #[getter]
    fn arena_size_m(&self) -> (f32, f32) {
        let [x, y] = self.world().arena.size_m;
        (x, y)
    }

    #[getter]
    fn arena_height_m(&self) -> f32 {
        self.world().arena.height_m
    }

    #[getter]
    fn scene_origin(&self) -> &str {
        &self.origin
    }

    /// The scene's TOML text (the seed and threads may differ: see `seed`, `threads`).
    #[getter]
    fn scene_toml(&self) -> &str {
        &self.text
    }

    /// The scene's static boxes as the engine has them: (name, centre (x, y, z) m, half
    /// extents m, yaw rad, virtual only).
    #[getter]
    #[allow(clippy::type_complexity)]
    fn boxes(&self) -> Vec<(String, (f32, f32, f32), (f32, f32, f32), f32, bool)> {
        let t = |v: sim_core::math::Vec3| (v.x, v.y, v.z);
        let world = self.world();
        world
            .boxes
            .iter()
            .map(|b| (b.name.clone(), t(b.center_m), t(b.half_extents_m), b.yaw_rad, b.virtual_only))
            .collect()
    }

    #[getter]
    fn threads(&self) -> usize {
        self.spec.sim.threads
    }

    /// The live view's address, while it serves.
    #[getter]
    fn foxglove_address(&self) -> Option<String> {
        self.live.as_ref().map(|(_, l)| l.local_addr().to_string())
    }

    /// The log file, while it is written.
    #[getter]
    fn log_path(&self) -> Option<PathBuf> {
        self.flight().recorder.path().map(|p| p.to_owned())
    }
}

impl Drop for Sim {
    fn drop(&mut self) {
        if let Err(e) = self.finish() {
            // Nobody is left to raise it to; say it where a user looks.
            eprintln!("twinswarm: {e}");
        }
    }
}

/// Steps independent Sims side by side on threads, without the GIL.
#[pyfunction]
#[pyo3(signature = (sims, steps=1))]
fn step_many(py: Python<'_>, mut sims: Vec<PyRefMut<'_, Sim>>, steps: u64) -> PyResult<()> {
    let mut refs: Vec<&mut Sim> = sims.iter_mut().map(|s| &mut **s).collect();
    py.detach(|| refs.par_iter_mut().map(|s| s.step_n(steps)).collect::<Result<Vec<()>, String>>())
        .map(|_| ())
        .map_err(PyRuntimeError::new_err)
}

/// The extension module.
#[pymodule]
fn _native(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<Sim>()?;
    m.add_function(wrap_pyfunction!(step_many, m)?)?;
    m.add("TRUTH_COLUMNS_COUNT", TRUTH_COLUMNS)?;
    m.add("SENSOR_COLUMNS_COUNT", SENSOR_COLUMNS)?;
    Ok(())
}

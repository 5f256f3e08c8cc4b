//! `twinswarm fit LOG.data [LOG.data …]`: system identification of the horizontal flight model
//! from real flights ([`bridge::realflight::fit`]): the attitude-to-position delay, the linear
//! damping, the sign mapping and an on-line trim, fitted leave-one-flight-out on every flight of
//! the logs ([`bridge::realflight::flights`]), and the prediction errors 1, 2 and 4 s ahead, from
//! the state a twin synced to the copter has at each start, of Twinswarm's current model, the
//! identified one, constant velocity and staying put; and the height loop's IR statistics.

use std::path::{Path, PathBuf};

use bridge::paparazzi::flightlog::FlightLog;
use bridge::realflight::fit::{FitOptions, FitReport, FlightInput, StateEstimate};
use bridge::realflight::{Flight, Series};

use crate::BadInput;

/// `twinswarm fit` arguments.
#[derive(Debug, clap::Args)]
pub struct FitArgs {
    /// Paparazzi server logs: NAME.data with NAME.log beside each.
    #[arg(required = true, value_name = "LOG.data")]
    pub files: Vec<PathBuf>,
    /// The aircraft (default: in each log, the one that sent the most).
    #[arg(long, value_name = "AC_ID")]
    pub ac_id: Option<u8>,
    /// Where each prediction's state comes from: `synced` (the model fitted to the sonars'
    /// last second up to the start, as a twin kept in step with the copter has it), `centred`
    /// (the same fit over a second centred on the start: it peeks half a second ahead) or
    /// `line` (a line through the track's last half second, its state a quarter second old:
    /// the estimate before the synced one). The on-line trim stays causal in each.
    #[arg(long, value_enum, default_value_t = StateArg::Synced)]
    pub state: StateArg,
    /// Shorthand for `--state centred`.
    #[arg(long, conflicts_with = "state")]
    pub centred_state: bool,
    /// Take the floor level off the identified model's attitude too, as the current model's
    /// (by default the identified model learns the AHRS's trim on line instead).
    #[arg(long)]
    pub level_from_floor: bool,
    /// Print the report as JSON.
    #[arg(long)]
    pub json: bool,
}

/// `--state`'s values.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum StateArg {
    /// The model fitted to the last second of readings up to the start (causal).
    Synced,
    /// The same over a second centred on the start (peeks half a second ahead).
    Centred,
    /// A line through the track's last half second (causal; the state a quarter second old).
    Line,
}

impl FitArgs {
    /// The options the arguments ask for.
    fn options(&self) -> FitOptions {
        let state = match (self.centred_state, self.state) {
            (true, _) | (_, StateArg::Centred) => StateEstimate::Centred,
            (_, StateArg::Synced) => StateEstimate::Synced,
            (_, StateArg::Line) => StateEstimate::Line,
        };
        FitOptions { state, level_from_floor: self.level_from_floor, ..FitOptions::default() }
    }
}

/// One log, read: its aircraft's series and flights.
struct LoadedLog {
    file: PathBuf,
    series: Series,
    flights: Vec<Flight>,
}

/// Reads `file` as `validate` does ([`FlightLog::open`], the aircraft that sent the most unless
/// `ac_id` names one, [`Series::of`]), and checks it has flights with sonar readings in them.
fn load(file: &Path, ac_id: Option<u8>) -> anyhow::Result<LoadedLog> {
    let log = FlightLog::open(file).map_err(|e| BadInput(e.into()))?;
    let ac_id = twinswarm::logcmd::aircraft_of(&log, ac_id, file)?;
    let series = Series::of(&log, ac_id);
    let flights = bridge::realflight::flights(&series);
    if flights.is_empty() {
        return Err(BadInput(anyhow::anyhow!(
            "{}: aircraft {ac_id}: no flight in the log (no IR height above the floor with the motors on)",
            file.display()
        ))
        .into());
    }
    let airborne = |t: f64| flights.iter().any(|f| t >= f.start_s && t <= f.end_s);
    if !series.sensors.iter().any(|s| s.sonar_m.is_some() && airborne(s.t_s)) {
        return Err(BadInput(anyhow::anyhow!(
            "{}: aircraft {ac_id}: no sonar readings in its {} flight(s) (FINKEN_SENSOR_MODEL or SONAR_ARRAY)",
            file.display(),
            flights.len()
        ))
        .into());
    }
    Ok(LoadedLog { file: file.to_path_buf(), series, flights })
}

/// Runs `twinswarm fit`.
pub fn run(args: &FitArgs) -> anyhow::Result<()> {
    let logs: Vec<LoadedLog> = args.files.iter().map(|f| load(f, args.ac_id)).collect::<anyhow::Result<_>>()?;
    let inputs: Vec<FlightInput<'_>> = logs
        .iter()
        .flat_map(|log| {
            let name =
                log.file.file_name().map_or_else(|| log.file.display().to_string(), |n| n.to_string_lossy().into());
            log.flights.iter().enumerate().map(move |(k, f)| FlightInput {
                label: format!("{name} flight {}", k + 1),
                series: &log.series,
                flight: *f,
            })
        })
        .collect();
    let opts = args.options();
    let report = bridge::realflight::fit::identify(&inputs, &opts).map_err(|e| {
        let files: Vec<String> = args.files.iter().map(|f| f.display().to_string()).collect();
        BadInput(anyhow::Error::new(e).context(files.join(", ")))
    })?;
    if args.json {
        outln!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        out!("{}", to_text(&report, &args.files));
    }
    Ok(())
}

/// What the state at each start is.
fn state_line(o: &FitOptions) -> String {
    match o.state {
        StateEstimate::Synced => format!(
            "  state at t0: synced (the model fitted to the sonars' last {:.1} s up to t0, gated looking back: causal)\n",
            o.state_window_s
        ),
        StateEstimate::Centred => format!(
            "  state at t0: the model fitted to the sonars' {:.1} s centred on t0 (peeks half of it ahead)\n",
            o.state_window_s
        ),
        StateEstimate::Line => format!(
            "  state at t0: a line through the track's last {:.1} s (causal; the state at its centre)\n",
            o.velocity_window_s
        ),
    }
}

/// `lo-hi` with `unit`, or one value where they agree.
fn span(lo: f64, hi: f64, digits: usize, unit: &str) -> String {
    if (hi - lo).abs() < 1e-9 { format!("{lo:.digits$} {unit}") } else { format!("{lo:.digits$}-{hi:.digits$} {unit}") }
}

/// The terminal report: models × horizons, then what was identified and what went in.
fn to_text(r: &FitReport, files: &[PathBuf]) -> String {
    let mut s = table_text(r, files);
    s += &state_line(&r.options);
    s += &identified_text(r);
    s += &height_text(r);
    for k in &r.skipped {
        s += &format!("  skipped {}: {}\n", k.label, k.reason);
    }
    s
}

/// The heading and the models × horizons table.
fn table_text(r: &FitReport, files: &[PathBuf]) -> String {
    let files: Vec<String> = files.iter().map(|f| f.display().to_string()).collect();
    let mut s = format!(
        "twinswarm fit: {} ({} flights scored, {}{})\n",
        files.join(", "),
        r.flights.len(),
        if r.leave_one_out { "leave-one-flight-out" } else { "ONE flight: fitted and scored in sample" },
        if r.skipped.is_empty() { String::new() } else { format!(", {} skipped", r.skipped.len()) }
    );
    s += &format!("  {:<22}", "prediction error (m)");
    for h in &r.options.horizons_s {
        s += &format!(" {:>13}", format!("{h:.0} s med/p95"));
    }
    s += "      n\n";
    for m in &r.models {
        s += &format!("  {:<22}", m.name);
        for h in &m.horizons {
            s += &format!(" {:>13}", format!("{:.2}/{:.2}", h.median_m, h.p95_m));
        }
        s += &format!(" {:>6}\n", m.horizons.iter().map(|h| h.n.to_string()).collect::<Vec<_>>().join("/"));
    }
    s
}

/// The current model, what was identified, the signs and the trim.
fn identified_text(r: &FitReport) -> String {
    let folds = &r.flights;
    let fold = |f: fn(&bridge::realflight::fit::Params) -> f64| {
        let lo = folds.iter().map(|x| f(&x.params)).fold(f64::INFINITY, f64::min);
        let hi = folds.iter().map(|x| f(&x.params)).fold(f64::NEG_INFINITY, f64::max);
        (lo, hi)
    };
    let (tau, k) = (fold(|p| p.delay_s), fold(|p| p.damping_per_s));
    let a = &r.all_flights;
    let (delays, dampings) = (&r.options.delays_s, &r.options.dampings_per_s);
    let edge =
        |v: f64, g: &bridge::realflight::fit::Range| (v - g.from).abs() < 1e-9 || (g.to - v).abs() < g.step / 2.0;
    let edges: Vec<&str> = [
        (folds.iter().any(|f| edge(f.params.delay_s, delays)) || edge(a.delay_s, delays)).then_some("τ"),
        (folds.iter().any(|f| edge(f.params.damping_per_s, dampings)) || edge(a.damping_per_s, dampings))
            .then_some("k"),
    ]
    .into_iter()
    .flatten()
    .collect();
    let mut s = format!(
        "  current: damping {:.2} /s, no delay, the floor level taken off, no trim, {}\n",
        r.options.current_damping_per_s, r.twinswarm_mapping
    );
    s += &format!(
        "  identified: delay τ {} (all flights: {:.2} s), damping k {} (all: {:.2} /s)\n",
        span(tau.0, tau.1, 2, "s"),
        a.delay_s,
        span(k.0, k.1, 2, "/s"),
        a.damping_per_s,
    );
    let prior = |axis: usize| {
        let lo = folds.iter().map(|f| f.trim_prior_rad[axis]).fold(f64::INFINITY, f64::min);
        let hi = folds.iter().map(|f| f.trim_prior_rad[axis]).fold(f64::NEG_INFINITY, f64::max);
        span(lo.to_degrees(), hi.to_degrees(), 2, "°")
    };
    s += &format!(
        "    trim b on line ({}): x {} y {} (from priors x {} y {}, the other flights' mean)\n",
        if r.options.level_from_floor { "attitude less the floor level" } else { "the AHRS's attitude as it is" },
        span(r.bias_rad[0][0].to_degrees(), r.bias_rad[0][1].to_degrees(), 2, "°"),
        span(r.bias_rad[1][0].to_degrees(), r.bias_rad[1][1].to_degrees(), 2, "°"),
        prior(0),
        prior(1),
    );
    if !edges.is_empty() {
        s += &format!(
            "    ({} at the end of its grid (τ {:.2}-{:.2} s, k {:.2}-{:.2} /s): the best lies at or beyond it)\n",
            edges.join(" and "),
            delays.from,
            delays.to,
            dampings.from,
            dampings.to
        );
    }
    let maps: std::collections::BTreeSet<String> = folds.iter().map(|f| f.params.mapping.to_string()).collect();
    let agrees = if a.mapping == r.twinswarm_mapping { "Twinswarm's" } else { "NOT Twinswarm's" };
    s +=
        &format!("  signs: {} ({agrees}; per fold: {})\n", a.mapping, maps.into_iter().collect::<Vec<_>>().join(" | "));
    let ev = |e: &bridge::realflight::fit::SignEvidence| {
        let m = |b: Option<bridge::realflight::fit::AxisBest>| {
            b.map_or("-".to_owned(), |b| format!("{:.3} m", b.mean_error_m))
        };
        format!("+ {} / − {}", m(e.plus), m(e.minus))
    };
    s += &format!(
        "    (mean error along the axis at each sign's best τ, k: x ← pitch {}; y ← roll {})\n",
        ev(&a.sign_evidence[0]),
        ev(&a.sign_evidence[1])
    );
    s
}

/// What went in, and the height loop per flight.
fn height_text(r: &FitReport) -> String {
    let n = &r.samples;
    let mut s = format!(
        "  samples: sonar x {} of {} readings kept, y {} of {}; {} grid points at {:.0} Hz (gaps x {}, y {}); {} starts every {:.1} s\n",
        n.kept[0],
        n.readings[0],
        n.kept[1],
        n.readings[1],
        n.grid_points,
        1.0 / r.options.grid_dt_s,
        n.gap_points[0],
        n.gap_points[1],
        n.starts,
        r.options.start_every_s
    );
    s += &format!(
        "  height (IR, take-off + {:.0} s to landing − {:.0} s)      mean     sd   range  noise sd\n",
        r.options.settle_after_take_off_s, r.options.settle_before_landing_s
    );
    let row = |label: &str, h: Option<bridge::realflight::fit::HeightStats>| match h {
        Some(h) => format!(
            "    {label:<50} {:>5.2} m {:>4.1} cm {:>4.1} cm {:>5.2} cm\n",
            h.mean_m,
            h.sd_m * 100.0,
            h.range_m * 100.0,
            h.noise_sd_m * 100.0
        ),
        None => format!("    {label:<50} -\n"),
    };
    for f in &r.flights {
        let label = format!(
            "{} (log {:.1}-{:.1} s, τ {:.2} s, k {:.2})",
            f.label, f.flight.start_s, f.flight.end_s, f.params.delay_s, f.params.damping_per_s
        );
        s += &row(&label, f.height);
    }
    s += &row("all flights", r.height);
    s
}

//! `twinswarm plot FILE --heatmap OUT.png --attitude OUT.png --sonar OUT.png`: the paper's
//! figures from a log. Text uses DejaVu Sans, embedded in the binary (no system fonts).

use std::path::Path;
use std::sync::Once;

use anyhow::Context;
use bridge::log::{LogFile, proto};
use plotters::coord::Shift;
use plotters::prelude::*;
use serde::Deserialize;

use crate::BadInput;
use crate::logcmd::read_error;

/// Font family name the embedded font is registered under.
const FONT: &str = "sans-serif";

/// Registers the embedded DejaVu Sans (once).
fn register_font() -> anyhow::Result<()> {
    static ONCE: Once = Once::new();
    let mut ok = true;
    ONCE.call_once(|| {
        ok = plotters::style::register_font(FONT, FontStyle::Normal, dejavu::sans::regular()).is_ok();
    });
    anyhow::ensure!(ok, "the embedded font could not be loaded");
    Ok(())
}

/// Heat-map panel size, px.
pub const HEATMAP_PANEL_PX: (u32, u32) = (560, 460);
/// Attitude and sonar figure size, px.
pub const FIGURE_PX: (u32, u32) = (1200, 800);
/// Heat-map cell, m (larger when the arena would need more than [`MAX_CELLS`] of them).
const CELL_M: f64 = 0.05;
/// Most heat-map cells per panel: the grid is sized from the file's metadata, so a crafted
/// log must not choose the allocation.
const MAX_CELLS: f64 = 1_000_000.0;
/// Largest arena side a log may claim, m.
const MAX_ARENA_M: f64 = 10_000.0;
/// Copters drawn in one line plot.
const MAX_LINES: usize = 8;

#[derive(Debug)]
struct StateRow {
    t_s: f64,
    /// How long this state stands for, s: until the copter's next state (a log holds a
    /// copter's last message until its next, see [`hold_times`]).
    hold_s: f64,
    id: usize,
    pos_m: [f32; 3],
    rpy_rad: [f32; 3],
}

#[derive(Debug)]
struct CommandRow {
    t_s: f64,
    id: usize,
    roll_rad: f32,
    pitch_rad: f32,
}

#[derive(Debug)]
struct SensorRow {
    t_s: f64,
    id: usize,
    sonar_m: [f32; 4],
}

#[derive(Clone, Debug, Deserialize)]
struct CopterMeta {
    name: String,
    kind: String,
    #[serde(default)]
    start_pos_m: Option<[f32; 3]>,
}

#[derive(Clone, Debug, Deserialize)]
struct BoxMeta {
    name: String,
    center_m: [f32; 3],
    size_m: [f32; 3],
    yaw_rad: f32,
}

/// What the plots need from a log.
#[derive(Debug, Default)]
pub struct PlotData {
    copters: Vec<CopterMeta>,
    arena_m: [f64; 2],
    boxes: Vec<BoxMeta>,
    dt_s: f64,
    states: Vec<StateRow>,
    commands: Vec<CommandRow>,
    sensors: Vec<SensorRow>,
}

impl PlotData {
    /// Reads the copters, the arena and the messages the plots use.
    pub fn load(file: &LogFile, need_commands: bool, need_sensors: bool) -> anyhow::Result<Self> {
        let info = file.info().map_err(read_error)?;
        let meta = info.metadata.get("twinswarm").ok_or_else(|| {
            BadInput(anyhow::anyhow!(
                "{}: no `twinswarm` metadata record: not a twinswarm run log",
                file.path().display()
            ))
        })?;
        let parse = |key: &str| -> anyhow::Result<serde_json::Value> {
            let text = meta.get(key).with_context(|| format!("metadata has no {key:?}"))?;
            serde_json::from_str(text).with_context(|| format!("metadata {key:?} is not JSON"))
        };
        let bad = |e: anyhow::Error| anyhow::Error::new(BadInput(e.context(format!("{}", file.path().display()))));
        let copters: Vec<CopterMeta> =
            serde_json::from_value(parse("copters").map_err(bad)?).map_err(|e| bad(e.into()))?;
        let arena_m: [f64; 2] =
            serde_json::from_value(parse("arena_size_m").map_err(bad)?).map_err(|e| bad(e.into()))?;
        // Logs from before boxes were recorded have none; present but malformed is an error.
        let boxes: Vec<BoxMeta> = match meta.get("boxes") {
            None => Vec::new(),
            Some(_) => serde_json::from_value(parse("boxes").map_err(bad)?).map_err(|e| bad(e.into()))?,
        };
        if arena_m.iter().any(|v| !v.is_finite() || *v <= 0.0 || *v > MAX_ARENA_M) {
            return Err(bad(anyhow::anyhow!(
                "metadata \"arena_size_m\" = {arena_m:?}: each side must be positive and at most {MAX_ARENA_M} m"
            )));
        }
        // Logs from before the step was recorded used the 50 ms default.
        let dt_s: f64 = match meta.get("control_dt_s") {
            None => 0.05,
            Some(text) => text.parse().ok().filter(|dt: &f64| dt.is_finite() && *dt > 0.0).ok_or_else(|| {
                bad(anyhow::anyhow!("metadata \"control_dt_s\" = {text:?} is not a positive number of seconds"))
            })?,
        };
        // A message with a vector of the wrong length is bad input, named with its place.
        fn rows<R>(
            bad: &impl Fn(anyhow::Error) -> anyhow::Error,
            topic: &str,
            rows: Vec<(u64, Result<R, String>)>,
        ) -> anyhow::Result<Vec<R>> {
            rows.into_iter()
                .map(|(t, r)| r.map_err(|e| bad(anyhow::anyhow!("{topic} at log time {t} ns: {e}"))))
                .collect()
        }
        let states = file.messages::<proto::CopterState>("/copters/state").map_err(read_error)?;
        let states = rows(
            &bad,
            "/copters/state",
            states
                .into_iter()
                .map(|(t, m)| {
                    let row = || {
                        Ok(StateRow {
                            t_s: m.t_s,
                            hold_s: 0.0,
                            id: m.id as usize,
                            pos_m: proto::fixed("pos_m", &m.pos_m)?,
                            rpy_rad: proto::fixed("rpy_rad", &m.rpy_rad)?,
                        })
                    };
                    (t, row())
                })
                .collect(),
        )?;
        // Logs from before the sampling was recorded logged every step.
        let every: u64 = match meta.get("log_every_ticks") {
            None => 1,
            Some(text) => text.parse().ok().filter(|n| *n > 0).ok_or_else(|| {
                bad(anyhow::anyhow!("metadata \"log_every_ticks\" = {text:?} is not a positive whole number"))
            })?,
        };
        // The last logged step, which may come after every copter's last state if all of
        // them were held at the end.
        let log_end_s = match (meta.get("epoch_unix_ns").and_then(|t| t.parse::<u64>().ok()), info.time_range_ns) {
            (Some(epoch), Some((_, t1))) => t1.saturating_sub(epoch) as f64 / 1e9,
            _ => f64::NEG_INFINITY,
        };
        let mut states = states;
        hold_times(&mut states, every as f64 * dt_s, log_end_s);
        let commands = if need_commands {
            let msgs = file.messages::<proto::CopterCommand>("/copters/command").map_err(read_error)?;
            let rows_of = msgs.into_iter().map(|(t, m)| {
                (t, Ok(CommandRow { t_s: m.t_s, id: m.id as usize, roll_rad: m.roll_rad, pitch_rad: m.pitch_rad }))
            });
            rows(&bad, "/copters/command", rows_of.collect())?
        } else {
            Vec::new()
        };
        let sensors = if need_sensors {
            let msgs = file.messages::<proto::CopterSensors>("/copters/sensors").map_err(read_error)?;
            // A message without sonars has none to draw (`log import` writes the IR-only
            // `FINKEN_IR_ADC` so); any other count than four is bad input.
            let rows_of = msgs.into_iter().filter(|(_, m)| !m.sonar_m.is_empty()).map(|(t, m)| {
                let row = proto::fixed("sonar_m", &m.sonar_m).map(|sonar_m| SensorRow {
                    t_s: m.t_s,
                    id: m.id as usize,
                    sonar_m,
                });
                (t, row)
            });
            rows(&bad, "/copters/sensors", rows_of.collect())?
        } else {
            Vec::new()
        };
        Ok(Self { copters, arena_m, boxes, dt_s, states, commands, sensors })
    }

    fn copter_id(&self, name: &str) -> Option<usize> {
        self.copters.iter().position(|c| c.name == name)
    }
}

/// Sets each state's [`StateRow::hold_s`]: the time to the same copter's next state, and for
/// its last one the time to the log's last step (the later of `log_end_s` and the last
/// state) plus one logging period `period_s`. With every copter on every step that is one
/// step each; with `--log-rate` it is the rate's period; a wreck at rest, written once a
/// second, stands for the whole second.
fn hold_times(states: &mut [StateRow], period_s: f64, log_end_s: f64) {
    let end_s = states.iter().map(|s| s.t_s).fold(log_end_s, f64::max) + period_s;
    let mut next_t: std::collections::HashMap<usize, f64> = std::collections::HashMap::new();
    for s in states.iter_mut().rev() {
        let next = next_t.insert(s.id, s.t_s).unwrap_or(end_s);
        s.hold_s = (next - s.t_s).max(0.0);
    }
}

/// The outputs of `twinswarm plot`.
#[derive(Debug, Default)]
pub struct PlotRequest<'a> {
    /// `--heatmap`.
    pub heatmap: Option<&'a Path>,
    /// `--attitude`.
    pub attitude: Option<&'a Path>,
    /// `--sonar`.
    pub sonar: Option<&'a Path>,
    /// `--copter` (for the sonar plot; default the first copter).
    pub copter: Option<&'a str>,
}

/// `twinswarm plot`.
pub fn plot(path: &Path, req: &PlotRequest<'_>) -> anyhow::Result<()> {
    if req.heatmap.is_none() && req.attitude.is_none() && req.sonar.is_none() {
        return Err(BadInput(anyhow::anyhow!("plot: give at least one of --heatmap, --attitude, --sonar")).into());
    }
    let data = load_plottable(path, req.attitude.is_some(), req.sonar.is_some())?;
    let sonar_id = match req.copter {
        None => 0,
        Some(name) => data.copter_id(name).ok_or_else(|| {
            let names: Vec<&str> = data.copters.iter().map(|c| c.name.as_str()).collect();
            BadInput(anyhow::anyhow!("--copter {name:?}: no such copter in the log (copters: {})", names.join(", ")))
        })?,
    };
    register_font()?;
    if let Some(out) = req.heatmap {
        let size = heatmap_size(&data);
        draw_png(out, size, |root| draw_heatmap(&data, root))?;
        println!("wrote {} ({}x{} px): position heat-map", out.display(), size.0, size.1);
    }
    if let Some(out) = req.attitude {
        draw_png(out, FIGURE_PX, |root| draw_attitude(&data, root))?;
        println!("wrote {} ({}x{} px): pitch and roll", out.display(), FIGURE_PX.0, FIGURE_PX.1);
    }
    if let Some(out) = req.sonar {
        draw_png(out, FIGURE_PX, |root| draw_sonar(&data, sonar_id, root))?;
        println!(
            "wrote {} ({}x{} px): sonars and y of {}",
            out.display(),
            FIGURE_PX.0,
            FIGURE_PX.1,
            data.copters[sonar_id].name
        );
    }
    Ok(())
}

/// Loads a log and draws every plot into memory, as `plot` would but writing no file: what
/// the `plot` fuzz target runs. Returns the bytes drawn.
pub fn draw_all_in_memory(path: &Path) -> anyhow::Result<usize> {
    let data = load_plottable(path, true, true)?;
    register_font()?;
    let mut drawn = draw_buffer(heatmap_size(&data), |root| draw_heatmap(&data, root))?.len();
    drawn += draw_buffer(FIGURE_PX, |root| draw_attitude(&data, root))?.len();
    drawn += draw_buffer(FIGURE_PX, |root| draw_sonar(&data, 0, root))?.len();
    Ok(drawn)
}

/// A log's plot data, refused (bad input) when there is nothing to plot: no copters in its
/// metadata, or no states.
fn load_plottable(path: &Path, need_commands: bool, need_sensors: bool) -> anyhow::Result<PlotData> {
    let file = LogFile::open(path).map_err(read_error)?;
    let data = PlotData::load(&file, need_commands, need_sensors)?;
    if data.copters.is_empty() {
        return Err(BadInput(anyhow::anyhow!("{}: its metadata lists no copters", path.display())).into());
    }
    if data.states.is_empty() {
        return Err(BadInput(anyhow::anyhow!("{}: no messages on /copters/state to plot", path.display())).into());
    }
    Ok(data)
}

type Area<'a> = DrawingArea<BitMapBackend<'a>, Shift>;
type DrawResult = Result<(), Box<dyn std::error::Error + 'static>>;

fn draw_png(out: &Path, size: (u32, u32), draw: impl FnOnce(&Area<'_>) -> DrawResult) -> anyhow::Result<()> {
    if let Some(dir) = out.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).with_context(|| format!("cannot create {}", dir.display()))?;
    }
    let root = BitMapBackend::new(out, size).into_drawing_area();
    draw(&root).map_err(|e| anyhow::anyhow!("cannot draw {}: {e}", out.display()))?;
    root.present().map_err(|e| anyhow::anyhow!("cannot write {}: {e}", out.display()))?;
    Ok(())
}

/// Draws into an RGB buffer: `w × h × 3` bytes.
fn draw_buffer(size: (u32, u32), draw: impl FnOnce(&Area<'_>) -> DrawResult) -> anyhow::Result<Vec<u8>> {
    let mut buf = vec![0u8; size.0 as usize * size.1 as usize * 3];
    {
        let root = BitMapBackend::with_buffer(&mut buf, size).into_drawing_area();
        draw(&root).map_err(|e| anyhow::anyhow!("cannot draw: {e}"))?;
        root.present().map_err(|e| anyhow::anyhow!("cannot draw: {e}"))?;
    }
    Ok(buf)
}

const PALETTE: [RGBColor; 8] = [
    RGBColor(31, 119, 180),
    RGBColor(214, 39, 40),
    RGBColor(44, 160, 44),
    RGBColor(255, 127, 14),
    RGBColor(148, 103, 189),
    RGBColor(140, 86, 75),
    RGBColor(227, 119, 194),
    RGBColor(23, 190, 207),
];

fn lighter(c: RGBColor) -> RGBColor {
    RGBColor(c.0 / 2 + 128, c.1 / 2 + 128, c.2 / 2 + 128)
}

/// Panels: one per copter up to 9, else one panel with all copters together.
fn heatmap_panels(data: &PlotData) -> Vec<Option<usize>> {
    if data.copters.len() <= 9 { (0..data.copters.len()).map(Some).collect() } else { vec![None] }
}

fn heatmap_grid(n: usize) -> (usize, usize) {
    let cols = (n as f64).sqrt().ceil().max(1.0) as usize;
    (n.div_ceil(cols), cols)
}

fn heatmap_size(data: &PlotData) -> (u32, u32) {
    let (rows, cols) = heatmap_grid(heatmap_panels(data).len());
    (HEATMAP_PANEL_PX.0 * cols as u32, HEATMAP_PANEL_PX.1 * rows as u32)
}

/// The heat-map cell: [`CELL_M`], or larger so that a panel has at most [`MAX_CELLS`].
fn heatmap_cell_m([sx, sy]: [f64; 2]) -> f64 {
    CELL_M.max((sx * sy / MAX_CELLS).sqrt())
}

fn draw_heatmap(data: &PlotData, root: &Area<'_>) -> DrawResult {
    root.fill(&WHITE)?;
    let panels = heatmap_panels(data);
    let (rows, cols) = heatmap_grid(panels.len());
    let areas = root.split_evenly((rows, cols));
    let [sx, sy] = data.arena_m;
    let (hx, hy) = (sx / 2.0, sy / 2.0);
    let cell_m = heatmap_cell_m(data.arena_m);
    let nx = (sx / cell_m).ceil() as usize;
    let ny = (sy / cell_m).ceil() as usize;
    for (panel, area) in panels.iter().zip(&areas) {
        let mut counts = vec![0f64; nx * ny];
        for s in data.states.iter().filter(|s| panel.is_none_or(|id| s.id == id)) {
            let (x, y) = (s.pos_m[0] as f64, s.pos_m[1] as f64);
            let (i, j) = (((x + hx) / cell_m).floor(), ((y + hy) / cell_m).floor());
            if i >= 0.0 && j >= 0.0 && (i as usize) < nx && (j as usize) < ny {
                counts[j as usize * nx + i as usize] += s.hold_s;
            }
        }
        let max = counts.iter().copied().fold(0.0, f64::max);
        let title = match panel {
            Some(id) => format!("{} ({})", data.copters[*id].name, data.copters[*id].kind),
            None => format!("all {} copters", data.copters.len()),
        };
        let caption = format!("{title}: time per {:.0} cm cell, max {:.1} s", cell_m * 100.0, max);
        let m = 0.15;
        let mut chart = ChartBuilder::on(area)
            .caption(caption, (FONT, 17))
            .margin(10)
            .x_label_area_size(40)
            .y_label_area_size(50)
            .build_cartesian_2d((-hx - m)..(hx + m), (-hy - m)..(hy + m))?;
        chart
            .configure_mesh()
            .disable_mesh()
            .x_desc("x (m)")
            .y_desc("y (m)")
            .label_style((FONT, 14))
            .axis_desc_style((FONT, 15))
            .draw()?;
        // Log colour scale, in control steps.
        let ln_max = (1.0 + max / data.dt_s).ln();
        chart.draw_series(counts.iter().enumerate().filter(|(_, c)| **c > 0.0).map(|(k, c)| {
            let (i, j) = ((k % nx) as f64, (k / nx) as f64);
            let t = (1.0 + *c / data.dt_s).ln() / ln_max;
            let lerp = |a: f64, b: f64| (a + (b - a) * t).round() as u8;
            let color = RGBColor(lerp(222.0, 8.0), lerp(235.0, 48.0), lerp(247.0, 107.0));
            let (x0, y0) = (-hx + i * cell_m, -hy + j * cell_m);
            Rectangle::new([(x0, y0), (x0 + cell_m, y0 + cell_m)], color.filled())
        }))?;
        // Arena outline and boxes.
        chart.draw_series(std::iter::once(PathElement::new(
            vec![(-hx, -hy), (hx, -hy), (hx, hy), (-hx, hy), (-hx, -hy)],
            BLACK.stroke_width(2),
        )))?;
        for b in &data.boxes {
            let (c, s) = (b.yaw_rad.cos() as f64, b.yaw_rad.sin() as f64);
            let (ex, ey) = (b.size_m[0] as f64 / 2.0, b.size_m[1] as f64 / 2.0);
            let corner = |u: f64, v: f64| (b.center_m[0] as f64 + c * u - s * v, b.center_m[1] as f64 + s * u + c * v);
            let pts = vec![corner(-ex, -ey), corner(ex, -ey), corner(ex, ey), corner(-ex, ey), corner(-ex, -ey)];
            chart.draw_series(std::iter::once(PathElement::new(pts, RGBColor(140, 80, 30).stroke_width(2))))?;
            chart.draw_series(std::iter::once(Text::new(
                b.name.clone(),
                corner(-ex, ey),
                (FONT, 12).into_font().color(&RGBColor(140, 80, 30)),
            )))?;
        }
        // Start positions.
        for (id, c) in data.copters.iter().enumerate() {
            if panel.is_some_and(|p| p != id) {
                continue;
            }
            if let Some(p) = c.start_pos_m {
                chart.draw_series(std::iter::once(Cross::new((p[0] as f64, p[1] as f64), 5, RED.stroke_width(2))))?;
            }
        }
    }
    Ok(())
}

/// Copters in line plots: the first [`MAX_LINES`].
fn line_copters(data: &PlotData) -> (Vec<usize>, String) {
    let n = data.copters.len();
    let ids: Vec<usize> = (0..n.min(MAX_LINES)).collect();
    let note = if n > MAX_LINES { format!(" (first {MAX_LINES} of {n} copters)") } else { String::new() };
    (ids, note)
}

fn time_range(data: &PlotData) -> std::ops::Range<f64> {
    let end = data.states.iter().map(|s| s.t_s).fold(0.0, f64::max);
    0.0..end.max(data.dt_s)
}

fn value_range(values: impl Iterator<Item = f64>, min_span: f64) -> std::ops::Range<f64> {
    let (lo, hi) = values.filter(|v| v.is_finite()).fold((f64::MAX, f64::MIN), |(a, b), v| (a.min(v), b.max(v)));
    if lo > hi {
        return -min_span..min_span;
    }
    let mid = (lo + hi) / 2.0;
    let half = ((hi - lo) / 2.0).max(min_span / 2.0) * 1.1;
    (mid - half)..(mid + half)
}

fn draw_attitude(data: &PlotData, root: &Area<'_>) -> DrawResult {
    root.fill(&WHITE)?;
    let (ids, note) = line_copters(data);
    let areas = root.split_evenly((2, 1));
    let t = time_range(data);
    for (axis, (area, name)) in areas.iter().zip(["pitch", "roll"]).enumerate() {
        // rpy_rad: [roll, pitch, yaw]; axis 0 = pitch.
        let k = if axis == 0 { 1 } else { 0 };
        let cmd_of = |c: &CommandRow| (if axis == 0 { c.pitch_rad } else { c.roll_rad }) as f64;
        let twins: Vec<usize> = ids.iter().copied().filter(|&id| data.copters[id].kind == "real").collect();
        let values = data
            .states
            .iter()
            .filter(|s| s.id < MAX_LINES)
            .map(|s| (s.rpy_rad[k] as f64).to_degrees())
            .chain(data.commands.iter().filter(|c| twins.contains(&c.id)).map(|c| cmd_of(c).to_degrees()));
        let y = value_range(values, 2.0);
        let mut chart = ChartBuilder::on(area)
            .caption(format!("{name} over time{note}"), (FONT, 20))
            .margin(12)
            .x_label_area_size(45)
            .y_label_area_size(60)
            .build_cartesian_2d(t.clone(), y)?;
        chart
            .configure_mesh()
            .x_desc("time (s)")
            .y_desc(format!("{name} (°)"))
            .label_style((FONT, 14))
            .axis_desc_style((FONT, 16))
            .light_line_style(RGBColor(235, 235, 235))
            .draw()?;
        for (n, &id) in ids.iter().enumerate() {
            let color = PALETTE[n % PALETTE.len()];
            let c = &data.copters[id];
            if c.kind == "real" {
                let cmd = data.commands.iter().filter(|r| r.id == id).map(|r| (r.t_s, cmd_of(r).to_degrees()));
                chart
                    .draw_series(LineSeries::new(cmd, lighter(color).stroke_width(3)))?
                    .label(format!("{} commanded", c.name))
                    .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], lighter(color).stroke_width(3)));
            }
            let series = data.states.iter().filter(|s| s.id == id).map(|s| (s.t_s, (s.rpy_rad[k] as f64).to_degrees()));
            let label = if c.kind == "real" { format!("{} twin", c.name) } else { c.name.clone() };
            chart
                .draw_series(LineSeries::new(series, color.stroke_width(1)))?
                .label(label)
                .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], color.stroke_width(2)));
        }
        draw_legend(&mut chart)?;
    }
    Ok(())
}

/// A chart of this module: time or log time against a value.
type Chart<'a, 'b> = ChartContext<
    'a,
    BitMapBackend<'b>,
    Cartesian2d<plotters::coord::types::RangedCoordf64, plotters::coord::types::RangedCoordf64>,
>;

/// The legend every line chart here has: upper right, on a light box.
fn draw_legend<'a, 'b: 'a>(chart: &mut Chart<'a, 'b>) -> DrawResult {
    chart
        .configure_series_labels()
        .label_font((FONT, 14))
        .background_style(WHITE.mix(0.85))
        .border_style(RGBColor(180, 180, 180))
        .position(SeriesLabelPosition::UpperRight)
        .draw()?;
    Ok(())
}

fn draw_sonar(data: &PlotData, id: usize, root: &Area<'_>) -> DrawResult {
    root.fill(&WHITE)?;
    let areas = root.split_evenly((2, 1));
    let t = time_range(data);
    let name = &data.copters[id].name;
    let readings: Vec<&SensorRow> = data.sensors.iter().filter(|s| s.id == id).collect();
    // No echo is infinite: left out of the lines and of the scale.
    let max = readings.iter().flat_map(|r| r.sonar_m).filter(|v| v.is_finite()).fold(1.0f32, f32::max) as f64;
    let mut chart = ChartBuilder::on(&areas[0])
        .caption(format!("{name}: sonar distances"), (FONT, 20))
        .margin(12)
        .x_label_area_size(45)
        .y_label_area_size(60)
        .build_cartesian_2d(t.clone(), 0.0..max * 1.05)?;
    chart
        .configure_mesh()
        .x_desc("time (s)")
        .y_desc("distance (m)")
        .label_style((FONT, 14))
        .axis_desc_style((FONT, 16))
        .light_line_style(RGBColor(235, 235, 235))
        .draw()?;
    for (k, label) in ["front", "right", "back", "left"].into_iter().enumerate() {
        let color = PALETTE[k];
        chart
            .draw_series(LineSeries::new(
                readings.iter().map(|r| (r.t_s, r.sonar_m[k] as f64)).filter(|p| p.1.is_finite()),
                color.stroke_width(1),
            ))?
            .label(label)
            .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], color.stroke_width(2)));
    }
    draw_legend(&mut chart)?;
    // A real flight's import has no position (NaN): the panel stays empty.
    let ys: Vec<(f64, f64)> = data
        .states
        .iter()
        .filter(|s| s.id == id)
        .map(|s| (s.t_s, s.pos_m[1] as f64))
        .filter(|p| p.1.is_finite())
        .collect();
    let y_range = value_range(ys.iter().map(|p| p.1), 0.2);
    let mut chart = ChartBuilder::on(&areas[1])
        .caption(format!("{name}: y position"), (FONT, 20))
        .margin(12)
        .x_label_area_size(45)
        .y_label_area_size(60)
        .build_cartesian_2d(t, y_range)?;
    chart
        .configure_mesh()
        .x_desc("time (s)")
        .y_desc("y (m)")
        .label_style((FONT, 14))
        .axis_desc_style((FONT, 16))
        .light_line_style(RGBColor(235, 235, 235))
        .draw()?;
    chart.draw_series(LineSeries::new(ys, BLACK.stroke_width(2)))?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use bridge::log::{LogMeta, Logger};

    fn temp_dir(tag: &str) -> std::path::PathBuf {
        let dir = std::env::temp_dir().join(format!("twinswarm-plot-{tag}-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        dir
    }

    /// A 6 s run of the lab with the second copter made a twin (kind real) flying a
    /// commanded pitch, logged.
    fn sample_log(dir: &Path) -> std::path::PathBuf {
        let text = sim_core::scene::DEFAULT_SCENE_TOML.replacen(
            "name = \"finken2\"\nkind = \"virtual\"",
            "name = \"finken2\"\nkind = \"real\"",
            1,
        );
        let (_, world) = sim_core::scene::load("test", &text).unwrap();
        let mut state = world.initial_state();
        let mut inputs = world.initial_inputs();
        inputs.commands[1].mode = sim_core::FlightMode::MixedManual;
        let path = dir.join("run.mcap");
        let mut log = Logger::create(&path, &world, &text, LogMeta::default()).unwrap();
        for k in 0..120 {
            inputs.commands[1].pitch_rad = if (k / 20) % 2 == 1 { 0.05 } else { -0.05 };
            let r = sim_core::step(&world, &mut state, &inputs);
            log.log_step(&world, &state, &inputs, &r).unwrap();
        }
        log.finish().unwrap();
        path
    }

    fn distinct_colors(buf: &[u8]) -> usize {
        let mut seen = std::collections::HashSet::new();
        for px in buf.chunks_exact(3) {
            seen.insert((px[0], px[1], px[2]));
            if seen.len() > 64 {
                break;
            }
        }
        seen.len()
    }

    #[test]
    fn plots_draw_something_and_write_pngs_of_the_expected_size() {
        register_font().unwrap();
        let dir = temp_dir("ok");
        let path = sample_log(&dir);
        let file = LogFile::open(&path).unwrap();
        let data = PlotData::load(&file, true, true).unwrap();
        assert_eq!(data.copters.len(), 2);
        // Every state the log holds (a copter still on the floor, unchanged, is not re-logged).
        let logged = file.messages::<proto::CopterState>("/copters/state").unwrap().len();
        assert!(logged > 120, "{logged} states logged");
        assert_eq!(data.states.len(), logged);
        assert_eq!(heatmap_size(&data), (HEATMAP_PANEL_PX.0 * 2, HEATMAP_PANEL_PX.1));
        for (what, buf) in [
            ("heatmap", draw_buffer(heatmap_size(&data), |a| draw_heatmap(&data, a)).unwrap()),
            ("attitude", draw_buffer(FIGURE_PX, |a| draw_attitude(&data, a)).unwrap()),
            ("sonar", draw_buffer(FIGURE_PX, |a| draw_sonar(&data, 0, a)).unwrap()),
        ] {
            assert!(distinct_colors(&buf) > 16, "{what} looks blank: {} colours", distinct_colors(&buf));
        }
        let outs = [dir.join("h.png"), dir.join("a.png"), dir.join("s.png")];
        let req = PlotRequest {
            heatmap: Some(&outs[0]),
            attitude: Some(&outs[1]),
            sonar: Some(&outs[2]),
            copter: Some("finken2"),
        };
        plot(&path, &req).unwrap();
        for (out, (w, h)) in outs.iter().zip([heatmap_size(&data), FIGURE_PX, FIGURE_PX]) {
            let png = std::fs::read(out).unwrap();
            assert_eq!(&png[..8], b"\x89PNG\r\n\x1a\n", "{}", out.display());
            let width = u32::from_be_bytes(png[16..20].try_into().unwrap());
            let height = u32::from_be_bytes(png[20..24].try_into().unwrap());
            assert_eq!((width, height), (w, h), "{}", out.display());
        }
        let _ = std::fs::remove_dir_all(&dir);
    }

    /// A real flight's log in the `default` telemetry mode (the 2015 fork's layout, reduced):
    /// `FINKEN_SENSOR_MODEL` every 0.1 s (sonars in cm, `pos_z`, the attitude), `FINKEN_IR_ADC`
    /// every 1 s (the IR only), no AHRS message; 20 s, imported as `log import` does.
    fn default_mode_import(dir: &Path) -> std::path::PathBuf {
        use bridge::paparazzi::flightlog::{FlightLog, LogConfig};
        let log = r#"<?xml version="1.0"?>
<configuration time_of_day="1448458956.0" data_file="d.data">
  <protocol>
    <msg_class NAME="telemetry">
      <message NAME="FINKEN_SENSOR_MODEL" ID="217">
        <field TYPE="int16" NAME="distance_d_front" ALT_UNIT="cm"/>
        <field TYPE="int16" NAME="distance_d_rigth" ALT_UNIT="cm"/>
        <field TYPE="int16" NAME="distance_d_left" ALT_UNIT="cm"/>
        <field TYPE="int16" NAME="distance_d_back" ALT_UNIT="cm"/>
        <field TYPE="float" NAME="pos_z" ALT_UNIT="m"/>
        <field TYPE="float" NAME="pos_pitch" ALT_UNIT="rad"/>
        <field TYPE="float" NAME="pos_roll" ALT_UNIT="rad"/>
        <field TYPE="float" NAME="pos_yaw" ALT_UNIT="rad"/>
      </message>
      <message NAME="FINKEN_IR_ADC" ID="252">
        <field TYPE="float" NAME="ir_distance" ALT_UNIT="cm"/>
        <field TYPE="uint16" NAME="ir_measurement"/>
      </message>
    </msg_class>
  </protocol>
</configuration>
"#;
        let config = LogConfig::parse(log, "d.log").unwrap();
        let mut data = String::new();
        for k in 0..200u32 {
            let t = f64::from(k) / 10.0;
            let roll = 0.1 * (t * 0.5).sin();
            let (front, back) = (150 + k % 7, 230 - k % 5);
            data += &format!("{t:.3} 6 FINKEN_SENSOR_MODEL {front} 140 160 {back} 0.5 0.02 {roll:.4} 1.5\n");
            if k % 10 == 3 {
                data += &format!("{:.3} 6 FINKEN_IR_ADC 0.5 2400\n", t + 0.05);
            }
        }
        let flight = FlightLog::from_parts(config, data.as_bytes(), "d.data");
        assert_eq!(flight.errors.total(), 0, "{:?}", flight.errors);
        let out = dir.join("default.mcap");
        bridge::log::import_flight(&flight, 6, &out, "test").unwrap();
        out
    }

    #[test]
    fn an_imported_default_mode_log_plots_its_sonars_and_its_attitude() {
        register_font().unwrap();
        let dir = temp_dir("default-mode");
        let path = default_mode_import(&dir);
        let file = LogFile::open(&path).unwrap();
        // The IR-only messages are on /copters/sensors without sonars.
        let sensors = file.messages::<proto::CopterSensors>("/copters/sensors").unwrap();
        assert_eq!(sensors.len(), 220);
        assert_eq!(sensors.iter().filter(|(_, m)| m.sonar_m.is_empty()).count(), 20);
        let data = PlotData::load(&file, true, true).unwrap();
        assert_eq!(data.sensors.len(), 200, "the messages with sonars");
        assert!(data.sensors.iter().all(|r| r.sonar_m.iter().all(|v| (1.0..2.4).contains(v))), "m, not cm");
        // Without an AHRS message the attitude is FINKEN_SENSOR_MODEL's, on /copters/state.
        assert_eq!(data.states.len(), 200);
        assert!(data.states.iter().any(|s| s.rpy_rad[0] > 0.09), "the roll it carries");
        let (att, sonar) = (dir.join("att.png"), dir.join("sonar.png"));
        plot(&path, &PlotRequest { attitude: Some(&att), sonar: Some(&sonar), ..PlotRequest::default() }).unwrap();
        for out in [&att, &sonar] {
            let png = std::fs::read(out).unwrap();
            assert!(png.len() > 1000 && png.starts_with(b"\x89PNG"), "{}", out.display());
        }
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn each_state_stands_for_the_time_to_its_copters_next() {
        let row = |t_s: f64, id: usize| StateRow { t_s, hold_s: f64::NAN, id, pos_m: [0.0; 3], rpy_rad: [0.0; 3] };
        // Copter 0 on every 50 ms step for 2 s; copter 1, a wreck at rest, once a second.
        let mut states = Vec::new();
        for k in 0..40 {
            let t_s = k as f64 * 0.05;
            states.push(row(t_s, 0));
            if k % 20 == 0 {
                states.push(row(t_s, 1));
            }
        }
        hold_times(&mut states, 0.05, f64::NEG_INFINITY);
        let total = |id: usize| states.iter().filter(|s| s.id == id).map(|s| s.hold_s).sum::<f64>();
        assert!((total(0) - 2.0).abs() < 1e-9, "{}", total(0));
        assert!((total(1) - 2.0).abs() < 1e-9, "{}", total(1));
        assert!(states.iter().filter(|s| s.id == 1).all(|s| (s.hold_s - 1.0).abs() < 1e-9));
        assert!(states.iter().filter(|s| s.id == 0).all(|s| (s.hold_s - 0.05).abs() < 1e-9));
        // The log goes on 0.5 s after the last state (every copter held at the end).
        hold_times(&mut states, 0.05, 2.45);
        let total = |id: usize| states.iter().filter(|s| s.id == id).map(|s| s.hold_s).sum::<f64>();
        assert!((total(0) - 2.5).abs() < 1e-9 && (total(1) - 2.5).abs() < 1e-9);
    }

    #[test]
    fn bad_files_give_clear_bad_input_errors() {
        let dir = temp_dir("bad");
        let good = sample_log(&dir);
        let bytes = std::fs::read(&good).unwrap();
        let cases = [
            ("empty.mcap", Vec::new(), "is empty"),
            ("text.mcap", b"name = \"lab\"\n".repeat(20), "not an MCAP file"),
            ("cut.mcap", bytes[..bytes.len() / 2].to_vec(), "truncated"),
        ];
        let out = dir.join("x.png");
        for (name, content, expect) in cases {
            let p = dir.join(name);
            std::fs::write(&p, content).unwrap();
            let req = PlotRequest { heatmap: Some(&out), ..PlotRequest::default() };
            let err = plot(&p, &req).unwrap_err();
            assert!(err.downcast_ref::<BadInput>().is_some(), "{name}: not a bad-input error: {err:#}");
            assert!(format!("{err:#}").contains(expect), "{name}: {err:#}");
            let err = crate::logcmd::info(&p).unwrap_err();
            assert!(err.downcast_ref::<BadInput>().is_some(), "{name}: info: {err:#}");
            assert!(format!("{err:#}").contains(expect), "{name}: info: {err:#}");
        }
        let missing = dir.join("missing.mcap");
        let err = crate::logcmd::info(&missing).unwrap_err();
        assert!(err.downcast_ref::<BadInput>().is_some(), "{err:#}");
        assert!(!out.exists());
        let _ = std::fs::remove_dir_all(&dir);
    }
}

/// One panel of [`draw_panels`]: a titled chart of lines over a shared x axis.
#[derive(Clone, Debug, Default)]
pub struct Panel {
    /// Caption.
    pub title: String,
    /// The y axis' description.
    pub y_desc: String,
    /// The lines, in legend order.
    pub lines: Vec<Line>,
}

/// One line of a [`Panel`].
#[derive(Clone, Debug, Default)]
pub struct Line {
    /// Legend label.
    pub label: String,
    /// Points (x, y); non-finite y values break nothing and are skipped.
    pub points: Vec<(f64, f64)>,
}

/// Draws `panels` stacked, one line colour per line index, into a PNG (e.g. the real copter's
/// attitude against its twins', `twinswarm validate --plots`).
pub fn draw_panels(out: &Path, x_desc: &str, panels: &[Panel]) -> anyhow::Result<()> {
    register_font()?;
    let height = 320 * panels.len().max(1) as u32;
    draw_png(out, (1400, height), |root| {
        root.fill(&WHITE)?;
        let areas = root.split_evenly((panels.len().max(1), 1));
        for (area, panel) in areas.iter().zip(panels) {
            draw_panel(area, x_desc, panel)?;
        }
        Ok(())
    })
}

fn draw_panel(area: &Area<'_>, x_desc: &str, panel: &Panel) -> DrawResult {
    let pts = || panel.lines.iter().flat_map(|l| l.points.iter()).filter(|p| p.1.is_finite());
    let (x0, x1) = pts().fold((f64::MAX, f64::MIN), |(a, b), p| (a.min(p.0), b.max(p.0)));
    let x = if x0 < x1 { x0..x1 } else { 0.0..1.0 };
    let y = value_range(pts().map(|p| p.1), 2.0);
    let mut chart = ChartBuilder::on(area)
        .caption(&panel.title, (FONT, 20))
        .margin(12)
        .x_label_area_size(45)
        .y_label_area_size(60)
        .build_cartesian_2d(x, y)?;
    chart
        .configure_mesh()
        .x_desc(x_desc)
        .y_desc(&panel.y_desc)
        .label_style((FONT, 14))
        .axis_desc_style((FONT, 16))
        .light_line_style(RGBColor(235, 235, 235))
        .draw()?;
    for (n, line) in panel.lines.iter().enumerate() {
        let color = PALETTE[n % PALETTE.len()];
        let width = if n == 0 { 3 } else { 1 };
        let style = if n == 0 { lighter(color).stroke_width(width) } else { color.stroke_width(width) };
        let series = line.points.iter().copied().filter(|p| p.1.is_finite());
        chart
            .draw_series(LineSeries::new(series, style))?
            .label(&line.label)
            .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], style));
    }
    draw_legend(&mut chart)?;
    Ok(())
}

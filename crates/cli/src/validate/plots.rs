//! `twinswarm validate --plots DIR`: per flight, the pitch and roll of the real copter against
//! its twins' (the report's Fig. 4.4-4.6), and the four sonars of the real copter against what
//! its twins' would read.

use std::path::Path;

use twinswarm::plot::{Line, Panel, draw_panels};

use super::FlightReport;

/// Writes `flight-K-attitude.png` and `flight-K-sonar.png` into `dir`.
pub fn draw(dir: &Path, f: &FlightReport) -> anyhow::Result<()> {
    let attitude: Vec<Panel> = ["pitch", "roll"]
        .iter()
        .map(|name| Panel {
            title: format!("flight {}: {name}", f.index),
            y_desc: format!("{name} (°)"),
            lines: f
                .curves
                .attitude
                .iter()
                .map(|(label, pts)| Line {
                    label: label.clone(),
                    points: pts.iter().map(|&(t, r, p)| (t, f64::from(if *name == "pitch" { p } else { r }))).collect(),
                })
                .collect(),
        })
        .collect();
    draw_panels(&dir.join(format!("flight-{}-attitude.png", f.index)), "log time (s)", &attitude)?;
    let sonar: Vec<Panel> = ["front", "right", "back", "left"]
        .iter()
        .enumerate()
        .map(|(k, name)| Panel {
            title: format!("flight {}: {name} sonar", f.index),
            y_desc: "distance (m)".into(),
            lines: f
                .curves
                .sonar
                .iter()
                .map(|(label, pts)| Line {
                    label: label.clone(),
                    points: pts.iter().map(|&(t, r)| (t, f64::from(r[k]))).collect(),
                })
                .collect(),
        })
        .collect();
    draw_panels(&dir.join(format!("flight-{}-sonar.png", f.index)), "log time (s)", &sonar)
}

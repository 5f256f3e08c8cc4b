//! What a virtual copter sends, and how often: a [`TelemetryPlan`], one mode of a Paparazzi
//! telemetry file (the project's own embedded as [`TELEMETRY_XML`]). The outbox sends virtual
//! copters' telemetry at its periods; the stand-in (`twinswarm copter`) and the sync evaluation
//! send a real copter's.

use crate::paparazzi::telemetry::Telemetry;

/// The project's telemetry plan (`assets/paparazzi/telemetry.xml`).
pub const TELEMETRY_XML: &str = include_str!("../../../../assets/paparazzi/telemetry.xml");

/// Which messages a copter sends, and how often: one mode of a telemetry file.
#[derive(Clone, Debug, PartialEq)]
pub struct TelemetryPlan {
    /// `<process>/<mode>` it came from.
    pub label: String,
    /// Message names and periods, s, in file order.
    pub periods: Vec<(String, f64)>,
}

impl TelemetryPlan {
    /// Mode `mode` (default: the first) of process `process` (default: the first).
    pub fn from_telemetry(t: &Telemetry, process: Option<&str>, mode: Option<&str>) -> Result<Self, String> {
        let p = match process {
            Some(name) => t.process(name).ok_or_else(|| format!("{}: no process `{name}`", t.source))?,
            None => t.processes.first().ok_or_else(|| format!("{}: no process", t.source))?,
        };
        let m = match mode {
            Some(name) => {
                p.mode(name).ok_or_else(|| format!("{}: process `{}` has no mode `{name}`", t.source, p.name))?
            }
            None => p.modes.first().ok_or_else(|| format!("{}: process `{}` has no mode", t.source, p.name))?,
        };
        Ok(Self {
            label: format!("{}/{}", p.name, m.name),
            periods: m.messages.iter().map(|msg| (msg.name.clone(), msg.period_s)).collect(),
        })
    }

    /// The embedded plan ([`TELEMETRY_XML`], first mode: `Main/mixed`).
    pub fn project_default() -> Self {
        let parsed = Telemetry::parse(TELEMETRY_XML, "assets/paparazzi/telemetry.xml")
            .map(|t| Self::from_telemetry(&t, None, None))
            .map_err(|e| e.to_string());
        match parsed {
            Ok(Ok(plan)) => plan,
            // Checked by a test; reaching this is a build defect.
            Ok(Err(e)) | Err(e) => panic!("the embedded telemetry.xml is invalid: {e}"),
        }
    }

    /// The period of `name`, if the plan sends it.
    pub fn period_s(&self, name: &str) -> Option<f64> {
        self.periods.iter().find(|(n, _)| n == name).map(|(_, p)| *p)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_embedded_plan_parses_and_sends_what_drives_a_twin_every_22_ms() {
        let plan = TelemetryPlan::project_default();
        assert_eq!(plan.label, "Main/mixed");
        assert_eq!(plan.period_s("FINKEN_ACTUATORS_SET_POINT"), Some(0.022));
        for (name, _) in &plan.periods {
            assert!(
                crate::paparazzi::convert::TELEMETRY_MESSAGES.contains(&name.as_str()),
                "{name} cannot be produced"
            );
        }
    }
}

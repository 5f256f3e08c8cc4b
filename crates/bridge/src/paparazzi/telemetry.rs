//! Paparazzi telemetry files (`conf/telemetry/*.xml`): which messages an
//! aircraft sends, and how often, in each mode.
//!
//! # Format
//!
//! ```xml
//! <telemetry>
//!   <process name="Main">
//!     <mode name="default" key_press="d">
//!       <message name="FINKEN_SENSOR_MODEL" period="0.1"/>
//!       <message name="ROTORCRAFT_FP" period="1"/>
//!     </mode>
//!     <mode name="extended">
//!       <message name="SONAR_ARRAY" period="1.0"/>
//!     </mode>
//!   </process>
//! </telemetry>
//! ```
//!
//! `process` has `name` and optional `type`; `mode` has `name` and optional
//! `key_press`; `message` has `name`, `period` (seconds, > 0; forms like
//! `.05` and `1.` occur) and optional `phase` (seconds) and `module`.
//! Unknown elements are errors; unknown attributes are ignored (they are
//! Paparazzi's files, not ours).

use std::collections::BTreeMap;
use std::path::Path;

use serde::Serialize;

use crate::paparazzi::xml::{Doc, Element, XmlError};

/// One `<message>` of a mode.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct PeriodicMessage {
    /// Message name.
    pub name: String,
    /// Period in seconds.
    pub period_s: f64,
    /// Phase offset in seconds, if given.
    pub phase_s: Option<f64>,
    /// Module that sends it, if given.
    pub module: Option<String>,
    /// Line of the element.
    pub source_line: u32,
}

/// One `<mode>`.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Mode {
    /// Mode name.
    pub name: String,
    /// Key that selects the mode in the GCS, if any.
    pub key_press: Option<String>,
    /// Messages in file order.
    pub messages: Vec<PeriodicMessage>,
}

impl Mode {
    /// Period in seconds of `message` in this mode (the first entry if the
    /// file lists the message twice).
    pub fn period_s(&self, message: &str) -> Option<f64> {
        self.messages.iter().find(|m| m.name == message).map(|m| m.period_s)
    }
}

/// One `<process>`.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Process {
    /// Process name (e.g. `Main`, `Logger`).
    pub name: String,
    /// `type` attribute, if any.
    pub kind: Option<String>,
    /// Modes in file order.
    pub modes: Vec<Mode>,
}

impl Process {
    /// The mode called `name`.
    pub fn mode(&self, name: &str) -> Option<&Mode> {
        self.modes.iter().find(|m| m.name == name)
    }

    /// For each message name, its period in seconds in each mode that
    /// sends it: `message -> (mode -> period_s)`, sorted by name.
    pub fn periods_by_message(&self) -> BTreeMap<&str, BTreeMap<&str, f64>> {
        let mut out: BTreeMap<&str, BTreeMap<&str, f64>> = BTreeMap::new();
        for mode in &self.modes {
            for m in &mode.messages {
                out.entry(m.name.as_str()).or_default().entry(mode.name.as_str()).or_insert(m.period_s);
            }
        }
        out
    }
}

/// A parsed telemetry file.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Telemetry {
    /// File label given at parse time.
    pub source: String,
    /// Processes in file order.
    pub processes: Vec<Process>,
}

impl Telemetry {
    /// Reads and parses a telemetry file.
    pub fn from_file(path: impl AsRef<Path>) -> Result<Telemetry, XmlError> {
        let path = path.as_ref();
        let text = crate::paparazzi::xml::read_file(path)?;
        Telemetry::parse(&text, &path.display().to_string())
    }

    /// Parses the text of a telemetry file; `source` labels error locations.
    pub fn parse(text: &str, source: &str) -> Result<Telemetry, XmlError> {
        let doc = Doc::parse(text, source)?;
        let root = doc.expect_root("telemetry")?;
        Telemetry::from_element(&doc, root, source)
    }

    /// The processes under a `<telemetry>` element of a parsed document (a telemetry file, or
    /// an aircraft's copy in a Paparazzi `server` log).
    pub(crate) fn from_element(doc: &Doc, root: &Element, source: &str) -> Result<Telemetry, XmlError> {
        let mut processes: Vec<Process> = Vec::new();
        for p in &root.children {
            if p.name != "process" {
                return Err(doc.unexpected(root, p));
            }
            let name = doc.req_attr(p, "name")?.value.trim().to_owned();
            if processes.iter().any(|q| q.name == name) {
                return Err(doc.invalid(p.offset, format!("duplicate process `{name}`")));
            }
            let kind = doc.attr(p, "type").map(|a| a.value.clone());
            let mut modes: Vec<Mode> = Vec::new();
            for m in &p.children {
                if m.name != "mode" {
                    return Err(doc.unexpected(p, m));
                }
                let mode = parse_mode(doc, m)?;
                if modes.iter().any(|x| x.name == mode.name) {
                    return Err(doc.invalid(m.offset, format!("duplicate mode `{}` in process `{name}`", mode.name)));
                }
                modes.push(mode);
            }
            processes.push(Process { name, kind, modes });
        }
        Ok(Telemetry { source: source.to_owned(), processes })
    }

    /// The process called `name`.
    pub fn process(&self, name: &str) -> Option<&Process> {
        self.processes.iter().find(|p| p.name == name)
    }
}

fn parse_mode(doc: &Doc, m: &Element) -> Result<Mode, XmlError> {
    let name = doc.req_attr(m, "name")?.value.trim().to_owned();
    let key_press = doc.attr(m, "key_press").map(|a| a.value.clone());
    let mut messages = Vec::new();
    for msg in &m.children {
        if msg.name != "message" {
            return Err(doc.unexpected(m, msg));
        }
        let msg_name = doc.req_attr(msg, "name")?.value.trim().to_owned();
        let period_attr = doc.req_attr(msg, "period")?;
        let period_s = doc.parse_f64_attr(msg, period_attr)?;
        if period_s <= 0.0 {
            return Err(doc.bad_attr(msg, period_attr, "period must be positive"));
        }
        let phase_s = match doc.attr(msg, "phase") {
            Some(a) => Some(doc.parse_f64_attr(msg, a)?),
            None => None,
        };
        messages.push(PeriodicMessage {
            name: msg_name,
            period_s,
            phase_s,
            module: doc.attr(msg, "module").map(|a| a.value.clone()),
            source_line: doc.line(msg.offset),
        });
    }
    Ok(Mode { name, key_press, messages })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_periods_and_rejects_bad_ones() {
        let ok = r#"<telemetry><process name="Main"><mode name="a">
            <message name="X" period=".05"/><message name="Y" period="1."/>
            </mode></process></telemetry>"#;
        let t = Telemetry::parse(ok, "t").expect("parses");
        let mode = t.process("Main").and_then(|p| p.mode("a")).expect("mode");
        assert_eq!(mode.period_s("X"), Some(0.05));
        assert_eq!(mode.period_s("Y"), Some(1.0));
        let bad = "<telemetry><process name=\"Main\"><mode name=\"a\">\n<message name=\"X\" period=\"0\"/></mode></process></telemetry>";
        let e = Telemetry::parse(bad, "t").expect_err("zero period");
        assert_eq!(e.line(), Some(2));
    }
}

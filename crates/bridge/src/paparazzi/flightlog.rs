//! Paparazzi `server` logs: a real flight as the ground segment recorded it.
//!
//! A log is a pair of files with one stem:
//!
//! - `NAME.log`: XML, `<configuration time_of_day=".." data_file="..">` holding `<conf>` (every
//!   aircraft of the lab's `conf.xml`, each with its airframe, flight plan, radio and telemetry
//!   file *as they were built*) and `<protocol>` (the `messages.xml` the ground segment used).
//!   `server` writes attribute names in upper case (`NAME`, `TYPE`, `ALT_UNIT_COEF`); they are
//!   read without regard to case, as Paparazzi reads them.
//! - `NAME.data`: one received message per line, `<time s> <sender> <NAME> <fields…>`, the time
//!   counted from `time_of_day`. `<sender> <NAME> <fields…>` is the Ivy text `link` put on the
//!   bus.
//!
//! The message definitions are always those of the `.log`: a lab's `messages.xml` is whatever
//! its fork said (the 2015 FINken fork's `FINKEN_SENSOR_MODEL` has 19 fields, one of them
//! `distance_d_rigth`), and no guessed file may stand in for it.
//!
//! Reading never panics. The `.log` must be valid (an [`XmlError`] names file, line and
//! column); a `.data` line that cannot be read is skipped and counted by cause in
//! [`LineErrors`], with the first few kept by line number, so one torn line of a long flight
//! costs that line only.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use serde::Serialize;

use crate::ids::AcId;
use crate::paparazzi::codec::{CodecError, Message, Sender, decode_payload, split_header};
use crate::paparazzi::messages::{MessageDef, MessageRef, MessageSet};
use crate::paparazzi::telemetry::Telemetry;
use crate::paparazzi::value::Value;
use crate::paparazzi::xml::{Doc, Element, XmlError};

/// How many unreadable lines are kept with their text; the rest are only counted.
pub const KEPT_LINE_ERRORS: usize = 20;

/// One aircraft of the log's `<conf>`.
#[derive(Clone, Debug, Serialize)]
pub struct LoggedAircraft {
    /// `name` (e.g. `FINken3_01`).
    pub name: String,
    /// `ac_id`.
    pub ac_id: AcId,
    /// The airframe file it was built from (`airframes/ovgu/fink3.xml`).
    pub airframe_file: String,
    /// The telemetry file it was built from.
    pub telemetry_file: String,
    /// Its telemetry processes and modes, as built (absent if the log has none).
    pub telemetry: Option<Telemetry>,
    /// The airframe's `<define NAME=.. VALUE=..>`s, keyed `SECTION.NAME` (`SECTION` empty for
    /// defines outside a section), in file order of first appearance.
    pub defines: BTreeMap<String, String>,
}

impl LoggedAircraft {
    /// The configured period of `message` in telemetry mode `mode` of the first process, s.
    pub fn period_s(&self, mode: &str, message: &str) -> Option<f64> {
        self.telemetry.as_ref()?.processes.first()?.mode(mode)?.period_s(message)
    }

    /// The telemetry mode whose messages best explain `seen` (the names the aircraft actually
    /// sent): the first mode that holds the most of them.
    pub fn mode_sending(&self, seen: &[&str]) -> Option<&str> {
        let process = self.telemetry.as_ref()?.processes.first()?;
        let score = |m: &&crate::paparazzi::telemetry::Mode| {
            seen.iter().filter(|s| m.messages.iter().any(|x| x.name == **s)).count()
        };
        let best = process.modes.iter().map(|m| score(&m)).max()?;
        process.modes.iter().find(|m| score(m) == best).map(|m| m.name.as_str())
    }
}

/// The `.log`: the configuration the flight was logged with.
#[derive(Clone, Debug)]
pub struct LogConfig {
    /// File label.
    pub source: String,
    /// Unix time of log time 0, s (`time_of_day`).
    pub time_of_day: Option<f64>,
    /// The `.data` file the log names.
    pub data_file: Option<String>,
    /// Every aircraft of the lab's configuration.
    pub aircraft: Vec<LoggedAircraft>,
    /// The message definitions the ground segment used.
    pub messages: MessageSet,
}

impl LogConfig {
    /// Parses the text of a `.log`; `source` labels error locations.
    pub fn parse(text: &str, source: &str) -> Result<LogConfig, XmlError> {
        let doc = Doc::parse(text, source)?;
        let root = doc.expect_root("configuration")?;
        let mut aircraft = Vec::new();
        let mut protocol = None;
        for child in &root.children {
            match child.name.as_str() {
                "conf" => {
                    for a in child.children.iter().filter(|a| a.name == "aircraft") {
                        aircraft.push(parse_aircraft(&doc, a, source)?);
                    }
                }
                "protocol" => protocol = Some(child),
                _ => {}
            }
        }
        let Some(protocol) = protocol else {
            return Err(doc.invalid(root.offset, "the log holds no <protocol> (message definitions)"));
        };
        let messages = MessageSet::from_element(&doc, protocol, source)?;
        let num = |name: &str| doc.attr(root, name).and_then(|a| a.value.trim().parse::<f64>().ok());
        Ok(LogConfig {
            source: source.to_owned(),
            time_of_day: num("time_of_day").filter(|t| t.is_finite()),
            data_file: doc.attr(root, "data_file").map(|a| a.value.clone()),
            aircraft,
            messages,
        })
    }

    /// The aircraft with `ac_id`.
    pub fn aircraft(&self, ac_id: AcId) -> Option<&LoggedAircraft> {
        self.aircraft.iter().find(|a| a.ac_id == ac_id)
    }
}

fn parse_aircraft(doc: &Doc, el: &Element, source: &str) -> Result<LoggedAircraft, XmlError> {
    let attr = |name: &str| doc.attr(el, name).map(|a| a.value.trim().to_owned()).unwrap_or_default();
    let id_attr = doc.req_attr(el, "ac_id")?;
    let ac_id: AcId = doc.parse_attr(el, id_attr, "an aircraft id 0..255")?;
    let telemetry = match el.children.iter().find(|c| c.name == "telemetry") {
        Some(t) => Some(Telemetry::from_element(doc, t, source)?),
        None => None,
    };
    let mut defines = BTreeMap::new();
    if let Some(airframe) = el.children.iter().find(|c| c.name == "airframe") {
        collect_defines(doc, airframe, "", &mut defines);
    }
    Ok(LoggedAircraft {
        name: attr("name"),
        ac_id,
        airframe_file: attr("airframe"),
        telemetry_file: attr("telemetry"),
        telemetry,
        defines,
    })
}

fn collect_defines(doc: &Doc, el: &Element, section: &str, out: &mut BTreeMap<String, String>) {
    for c in &el.children {
        match c.name.as_str() {
            "section" => {
                let prefix = doc.attr(c, "prefix").map(|a| a.value.trim()).unwrap_or("");
                collect_defines(doc, c, prefix, out);
            }
            "define" => {
                if let (Some(n), Some(v)) = (doc.attr(c, "name"), doc.attr(c, "value")) {
                    out.entry(format!("{section}{}", n.value.trim())).or_insert_with(|| v.value.trim().to_owned());
                }
            }
            _ => collect_defines(doc, c, section, out),
        }
    }
}

/// One message of the `.data`.
#[derive(Clone, Debug)]
pub struct Record {
    /// Log time, s.
    pub time_s: f64,
    /// Line number in the `.data`, from 1.
    pub line: u32,
    /// Who sent it (an aircraft for telemetry).
    pub sender: Sender,
    /// Its definition in the log's [`LogConfig::messages`].
    pub def: MessageRef,
    /// Its fields, typed by the definition.
    pub values: Vec<Value>,
    /// Byte range of the Ivy text (`<sender> <NAME> <fields…>`) in the `.data`.
    text: (usize, usize),
}

/// `.data` lines that could not be read, by cause, with the first [`KEPT_LINE_ERRORS`] kept.
#[derive(Clone, Debug, Default, Serialize)]
pub struct LineErrors {
    /// Count by cause (`bad time`, `no message name`, `unknown message`, `undecodable fields`,
    /// `bad sender`, `not text`).
    pub by_cause: BTreeMap<&'static str, u64>,
    /// The first few: line number and what was wrong.
    pub first: Vec<(u32, String)>,
    /// Lines whose time is earlier than the line before (kept, in file order).
    pub out_of_order: u64,
    /// Unreadable lines by message name, where the line had one.
    pub by_message: BTreeMap<String, u64>,
}

impl LineErrors {
    /// Unreadable lines in all.
    pub fn total(&self) -> u64 {
        self.by_cause.values().sum()
    }

    fn record(&mut self, line: u32, cause: &'static str, what: String) {
        *self.by_cause.entry(cause).or_default() += 1;
        if self.first.len() < KEPT_LINE_ERRORS {
            self.first.push((line, what));
        }
    }
}

/// Why a log could not be opened.
#[derive(Debug, thiserror::Error)]
pub enum FlightLogError {
    /// One file of the pair is not there.
    #[error("{path} does not exist: a Paparazzi log is NAME.data with NAME.log beside it")]
    Missing {
        /// The file that is not there.
        path: String,
    },
    /// A file could not be read. The cause is in the message, and not also a `source`: printed
    /// with its chain (`{:#}`, as the command line prints errors), it is named once.
    #[error("cannot read {path}: {cause}")]
    Io {
        /// The file.
        path: String,
        /// Why.
        cause: std::io::Error,
    },
    /// The `.log` is not a Paparazzi server log.
    #[error(transparent)]
    Config(#[from] XmlError),
    /// The path names neither a `.data` nor a `.log`.
    #[error("{0}: expected a Paparazzi log, NAME.data with NAME.log beside it")]
    NotALog(String),
}

/// A Paparazzi log: its configuration and every readable message, in file order.
#[derive(Debug)]
pub struct FlightLog {
    /// The `.log`.
    pub config: LogConfig,
    /// The `.data` file label.
    pub data_source: String,
    /// Readable messages, in file order.
    pub records: Vec<Record>,
    /// Unreadable lines.
    pub errors: LineErrors,
    /// Non-empty lines of the `.data`.
    pub lines: u64,
    data: String,
}

impl FlightLog {
    /// Opens `NAME.data` (or `NAME.log`) and the other file of the pair.
    pub fn open(path: &Path) -> Result<FlightLog, FlightLogError> {
        let (log_path, data_path) = pair_paths(path)?;
        let read = |p: &PathBuf| {
            std::fs::read(p).map_err(|cause| {
                let path = p.display().to_string();
                match cause.kind() {
                    std::io::ErrorKind::NotFound => FlightLogError::Missing { path },
                    _ => FlightLogError::Io { path, cause },
                }
            })
        };
        let log_bytes = read(&log_path)?;
        let log_text = String::from_utf8_lossy(&log_bytes);
        let data_bytes = read(&data_path)?;
        let config = LogConfig::parse(&log_text, &log_path.display().to_string())?;
        Ok(FlightLog::from_parts(config, &data_bytes, &data_path.display().to_string()))
    }

    /// Reads the `.data` bytes against an already parsed `.log`.
    pub fn from_parts(config: LogConfig, data: &[u8], data_source: &str) -> FlightLog {
        let mut errors = LineErrors::default();
        let data = match std::str::from_utf8(data) {
            Ok(s) => s.to_owned(),
            // Keep the readable lines of a file with a few torn bytes.
            Err(_) => String::from_utf8_lossy(data).into_owned(),
        };
        let mut records = Vec::new();
        let mut lines = 0;
        let mut last_time = f64::NEG_INFINITY;
        let mut offset = 0;
        for (i, raw) in data.split_inclusive('\n').enumerate() {
            let start = offset;
            offset += raw.len();
            let line = u32::try_from(i + 1).unwrap_or(u32::MAX);
            let text = raw.trim_end_matches(['\n', '\r']);
            if text.trim().is_empty() {
                continue;
            }
            lines += 1;
            match read_line(&config.messages, text, start, line) {
                Ok(r) => {
                    if r.time_s < last_time {
                        errors.out_of_order += 1;
                    }
                    last_time = r.time_s;
                    records.push(r);
                }
                Err((cause, what)) => {
                    if let Some((_, name, _)) =
                        text.split_once(' ').and_then(|(_, rest)| split_header(rest.trim_start()))
                    {
                        *errors.by_message.entry(name.to_owned()).or_default() += 1;
                    }
                    errors.record(line, cause, what);
                }
            }
        }
        FlightLog { config, data_source: data_source.to_owned(), records, errors, lines, data }
    }

    /// The Ivy text of a record, as `link` put it on the bus.
    pub fn text(&self, r: &Record) -> &str {
        self.data.get(r.text.0..r.text.1).unwrap_or("")
    }

    /// The definition of a record.
    pub fn def(&self, r: &Record) -> &MessageDef {
        self.config.messages.get(r.def)
    }

    /// A record as a decoded message.
    pub fn message(&self, r: &Record) -> Message<'_> {
        Message { sender: r.sender.clone(), def: self.def(r), values: r.values.clone() }
    }

    /// Records from aircraft `ac_id`.
    pub fn from_aircraft(&self, ac_id: AcId) -> impl Iterator<Item = &Record> {
        self.records.iter().filter(move |r| r.sender.ac_id() == Some(ac_id))
    }

    /// The aircraft that sent messages, with their counts, by id.
    pub fn senders(&self) -> BTreeMap<AcId, u64> {
        let mut out = BTreeMap::new();
        for r in &self.records {
            if let Some(ac) = r.sender.ac_id() {
                *out.entry(ac).or_default() += 1;
            }
        }
        out
    }

    /// The aircraft that sent the most records: the one a log of one flight is about.
    pub fn busiest_sender(&self) -> Option<AcId> {
        self.senders().into_iter().max_by_key(|(_, n)| *n).map(|(a, _)| a)
    }

    /// Log time of the first and last record, s.
    pub fn span_s(&self) -> Option<(f64, f64)> {
        Some((self.records.first()?.time_s, self.records.last()?.time_s))
    }
}

/// `NAME.log` and `NAME.data` for a path to either.
pub fn pair_paths(path: &Path) -> Result<(PathBuf, PathBuf), FlightLogError> {
    match path.extension().and_then(|e| e.to_str()) {
        Some("data") | Some("log") => Ok((path.with_extension("log"), path.with_extension("data"))),
        _ => Err(FlightLogError::NotALog(path.display().to_string())),
    }
}

/// Whether `path` looks like one file of a Paparazzi log pair (`.data`, or `.log` with a
/// `.data` beside it).
pub fn is_flight_log(path: &Path) -> bool {
    match path.extension().and_then(|e| e.to_str()) {
        Some("data") => true,
        Some("log") => path.with_extension("data").exists(),
        _ => false,
    }
}

type LineError = (&'static str, String);

fn read_line(messages: &MessageSet, text: &str, start: usize, line: u32) -> Result<Record, LineError> {
    let excerpt = || text.chars().take(80).collect::<String>();
    let (time, rest) = text.split_once(' ').ok_or_else(|| ("no message name", excerpt()))?;
    let time_s: f64 = match time.parse::<f64>() {
        Ok(t) if t.is_finite() => t,
        _ => return Err(("bad time", format!("`{time}` is not a time in seconds"))),
    };
    let rest = rest.trim_start_matches(' ');
    let text_start = start + (text.len() - rest.len());
    let (sender, name, payload) = split_header(rest).ok_or_else(|| ("no message name", excerpt()))?;
    let sender = Sender::parse(sender).map_err(|e| ("bad sender", e.to_string()))?;
    let refs = messages.refs_by_name(name);
    let def = match refs {
        [] => return Err(("unknown message", format!("{name} is not in the log's message definitions"))),
        [one] => *one,
        many => {
            let tm = many.iter().find(|r| messages.get(**r).class_name == "telemetry");
            *tm.filter(|_| sender.ac_id().is_some()).unwrap_or(&many[0])
        }
    };
    let values =
        decode_payload(messages.get(def), payload).map_err(|e: CodecError| ("undecodable fields", e.to_string()))?;
    Ok(Record { time_s, line, sender, def, values, text: (text_start, start + text.len()) })
}

#[cfg(test)]
mod tests {
    use super::*;

    const LOG: &str = r#"<?xml version="1.0"?>
<configuration time_of_day="1450270500.61" data_file="t.data">
  <conf>
    <aircraft name="FINken3_01" ac_id="5" airframe="airframes/ovgu/fink3.xml" telemetry="telemetry/x.xml">
      <airframe NAME="Fink3">
        <section NAME="MISC" PREFIX="MISC_"><define NAME="HEIGHT" VALUE="0.6"/></section>
      </airframe>
      <telemetry>
        <process NAME="Main">
          <mode NAME="vrep"><message PERIOD="0.022" NAME="POS"/></mode>
          <mode NAME="default"><message PERIOD="1.0" NAME="OTHER"/></mode>
        </process>
      </telemetry>
    </aircraft>
  </conf>
  <protocol>
    <msg_class NAME="telemetry">
      <message NAME="POS" ID="1">
        <field TYPE="int16" NAME="front" ALT_UNIT="cm"/>
        <field TYPE="float" NAME="z"/>
      </message>
    </msg_class>
  </protocol>
</configuration>
"#;

    #[test]
    fn reads_definitions_aircraft_and_lines_with_upper_case_attributes() {
        let config = LogConfig::parse(LOG, "t.log").expect("parses");
        assert_eq!(config.time_of_day, Some(1450270500.61));
        let a = config.aircraft(5).expect("aircraft 5");
        assert_eq!(a.name, "FINken3_01");
        assert_eq!(a.period_s("vrep", "POS"), Some(0.022));
        assert_eq!(a.mode_sending(&["POS"]), Some("vrep"));
        assert_eq!(a.defines.get("MISC_HEIGHT").map(String::as_str), Some("0.6"));
        let data = "3.410 5 POS 183 0.\n3.5 5 POS 1\nx 5 POS 1 2\n4.0 5 NOPE 1\n\n3.3 5 POS 7 0.25\n4.1\n";
        let log = FlightLog::from_parts(config, data.as_bytes(), "t.data");
        assert_eq!(log.records.len(), 2);
        assert_eq!(log.lines, 6);
        assert_eq!(log.text(&log.records[0]), "5 POS 183 0.");
        assert_eq!(log.records[1].line, 6);
        assert_eq!(log.errors.out_of_order, 1);
        assert_eq!(log.errors.by_cause.get("undecodable fields"), Some(&1));
        assert_eq!(log.errors.by_cause.get("bad time"), Some(&1));
        assert_eq!(log.errors.by_cause.get("unknown message"), Some(&1));
        assert_eq!(log.errors.by_cause.get("no message name"), Some(&1));
        assert_eq!(log.errors.first[0].0, 2);
        let m = log.message(&log.records[1]);
        assert_eq!(m.get("z").and_then(Value::as_f64), Some(0.25));
    }

    #[test]
    fn a_data_file_without_its_log_names_the_missing_file_and_the_cause_once() {
        let dir = std::env::temp_dir().join(format!("twinswarm-flightlog-pair-{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("tmp");
        let data = dir.join("lonely.data");
        std::fs::write(&data, "1.0 5 POS 1 0.5\n").expect("data");
        let e = FlightLog::open(&data).expect_err("no .log beside it");
        assert!(matches!(e, FlightLogError::Missing { .. }), "{e:?}");
        // As the command line prints it: the message and its whole chain of sources.
        let mut text = e.to_string();
        let mut source = std::error::Error::source(&e);
        while let Some(cause) = source {
            text += &format!(": {cause}");
            source = std::error::Error::source(cause);
        }
        assert!(text.contains("lonely.log does not exist"), "{text}");
        assert_eq!(text.matches("does not exist").count(), 1, "{text}");
        assert!(!text.contains("os error"), "the cause once, in words: {text}");
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn a_log_without_definitions_is_an_error_with_its_place() {
        let e = LogConfig::parse("<configuration>\n<conf/></configuration>", "x.log").expect_err("no protocol");
        assert!(e.to_string().contains("x.log:1"), "{e}");
    }
}

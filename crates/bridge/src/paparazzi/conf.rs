//! Paparazzi `conf.xml`: the list of aircraft.
//!
//! # Format
//!
//! ```xml
//! <conf>
//!   <aircraft name="FINken3_01" ac_id="5"
//!     airframe="airframes/ovgu/fink3_max_bgr.xml" radio="radios/spektrum.xml"
//!     telemetry="telemetry/ovgu/free_flight.xml"
//!     flight_plan="flight_plans/ovgu/free_flight.xml"
//!     settings="settings/rotorcraft_basic.xml settings/control/rotorcraft_guidance.xml"
//!     settings_modules="modules/ws2801.xml" gui_color="#fe32ffff0000"/>
//! </conf>
//! ```
//!
//! `name` and `ac_id` (0..=255, unique) are required and names must be
//! unique; the other attributes are optional here (Paparazzi's own tools
//! require most of them). `settings` and `settings_modules` are
//! space-separated path lists. Unknown attributes of `<aircraft>` are kept in
//! [`Aircraft::extra`] (newer Paparazzi versions add some); any element other
//! than `<aircraft>` inside `<conf>` is an error.
//!
//! The original FINken system decided from the aircraft name whether a
//! copter is virtual: names starting with `Virtual` are virtual, all others
//! real ([`AircraftKind::from_name`]).

use std::collections::BTreeMap;
use std::path::Path;

use serde::Serialize;

use crate::ids::AcId;
use crate::paparazzi::xml::{Doc, XmlError};

/// Whether an aircraft exists physically or only in the simulation.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum AircraftKind {
    /// A physical copter, twinned in the simulation.
    Real,
    /// A copter that exists only in the simulation.
    Virtual,
}

impl AircraftKind {
    /// The original system's default rule: names beginning with `Virtual`
    /// (case-sensitive) are virtual, all others are real.
    pub fn from_name(name: &str) -> AircraftKind {
        if is_virtual_name(name) { AircraftKind::Virtual } else { AircraftKind::Real }
    }
}

/// `true` if `name` begins with `Virtual` (the original system's rule).
pub fn is_virtual_name(name: &str) -> bool {
    name.starts_with("Virtual")
}

/// One `<aircraft>` entry.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Aircraft {
    /// Aircraft name.
    pub name: String,
    /// Aircraft id used as the Ivy sender of its telemetry.
    pub ac_id: AcId,
    /// Airframe file, relative to `conf/`.
    pub airframe: Option<String>,
    /// Radio file.
    pub radio: Option<String>,
    /// Telemetry file.
    pub telemetry: Option<String>,
    /// Flight plan file.
    pub flight_plan: Option<String>,
    /// Settings files (space-separated in the XML).
    pub settings: Vec<String>,
    /// Module settings files (space-separated in the XML).
    pub settings_modules: Vec<String>,
    /// GUI colour (a colour name or `#rrrrggggbbbb`).
    pub gui_color: Option<String>,
    /// Other attributes, by name.
    pub extra: BTreeMap<String, String>,
    /// Line of the `<aircraft>` element.
    pub source_line: u32,
}

impl Aircraft {
    /// Real or virtual, by the name rule.
    pub fn kind(&self) -> AircraftKind {
        AircraftKind::from_name(&self.name)
    }
}

/// A parsed `conf.xml`.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ConfXml {
    /// File label given at parse time.
    pub source: String,
    /// Aircraft in file order.
    pub aircraft: Vec<Aircraft>,
}

impl ConfXml {
    /// Reads and parses a `conf.xml` file.
    pub fn from_file(path: impl AsRef<Path>) -> Result<ConfXml, XmlError> {
        let path = path.as_ref();
        let text = crate::paparazzi::xml::read_file(path)?;
        ConfXml::parse(&text, &path.display().to_string())
    }

    /// Parses the text of a `conf.xml`; `source` labels error locations.
    pub fn parse(text: &str, source: &str) -> Result<ConfXml, XmlError> {
        let doc = Doc::parse(text, source)?;
        let root = doc.expect_root("conf")?;
        let mut aircraft: Vec<Aircraft> = Vec::new();
        let mut names: BTreeMap<String, u32> = BTreeMap::new();
        let mut ids: BTreeMap<AcId, u32> = BTreeMap::new();
        for el in &root.children {
            if el.name != "aircraft" {
                return Err(doc.unexpected(root, el));
            }
            let line = doc.line(el.offset);
            let name_attr = doc.req_attr(el, "name")?;
            let name = name_attr.value.trim().to_owned();
            if name.is_empty() {
                return Err(doc.bad_attr(el, name_attr, "aircraft name is empty"));
            }
            let id_attr = doc.req_attr(el, "ac_id")?;
            let ac_id: AcId = doc.parse_attr(el, id_attr, "an aircraft id 0..255")?;
            if let Some(first) = names.insert(name.clone(), line) {
                return Err(XmlError::Duplicate {
                    at: doc.loc(name_attr.offset),
                    what: "aircraft name",
                    name,
                    first_line: first,
                });
            }
            if let Some(first) = ids.insert(ac_id, line) {
                return Err(XmlError::Duplicate {
                    at: doc.loc(id_attr.offset),
                    what: "aircraft ac_id",
                    name: ac_id.to_string(),
                    first_line: first,
                });
            }
            let opt = |key: &str| doc.attr(el, key).map(|a| a.value.trim().to_owned()).filter(|v| !v.is_empty());
            let list = |key: &str| {
                doc.attr(el, key).map(|a| a.value.split_whitespace().map(str::to_owned).collect()).unwrap_or_default()
            };
            const KNOWN: [&str; 9] = [
                "name",
                "ac_id",
                "airframe",
                "radio",
                "telemetry",
                "flight_plan",
                "settings",
                "settings_modules",
                "gui_color",
            ];
            let extra = el
                .attrs
                .iter()
                .filter(|a| !KNOWN.contains(&a.name.as_str()))
                .map(|a| (a.name.clone(), a.value.clone()))
                .collect();
            aircraft.push(Aircraft {
                name,
                ac_id,
                airframe: opt("airframe"),
                radio: opt("radio"),
                telemetry: opt("telemetry"),
                flight_plan: opt("flight_plan"),
                settings: list("settings"),
                settings_modules: list("settings_modules"),
                gui_color: opt("gui_color"),
                extra,
                source_line: line,
            });
        }
        Ok(ConfXml { source: source.to_owned(), aircraft })
    }

    /// The aircraft called `name`.
    pub fn by_name(&self, name: &str) -> Option<&Aircraft> {
        self.aircraft.iter().find(|a| a.name == name)
    }

    /// The aircraft with id `ac_id`.
    pub fn by_ac_id(&self, ac_id: AcId) -> Option<&Aircraft> {
        self.aircraft.iter().find(|a| a.ac_id == ac_id)
    }

    /// Aircraft that are real by the name rule, in file order.
    pub fn real(&self) -> impl Iterator<Item = &Aircraft> {
        self.aircraft.iter().filter(|a| a.kind() == AircraftKind::Real)
    }

    /// Aircraft that are virtual by the name rule, in file order.
    pub fn virtual_aircraft(&self) -> impl Iterator<Item = &Aircraft> {
        self.aircraft.iter().filter(|a| a.kind() == AircraftKind::Virtual)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn virtual_rule() {
        assert_eq!(AircraftKind::from_name("Virtual_01"), AircraftKind::Virtual);
        assert_eq!(AircraftKind::from_name("VirtualFINken"), AircraftKind::Virtual);
        assert_eq!(AircraftKind::from_name("FINken3_01"), AircraftKind::Real);
        assert_eq!(AircraftKind::from_name("virtual_01"), AircraftKind::Real);
        assert_eq!(AircraftKind::from_name("My_Virtual"), AircraftKind::Real);
    }

    #[test]
    fn errors_have_lines() {
        let dup = "<conf>\n<aircraft name=\"A\" ac_id=\"1\"/>\n<aircraft name=\"B\"\n ac_id=\"1\"/>\n</conf>";
        let e = ConfXml::parse(dup, "c.xml").expect_err("dup id");
        assert!(matches!(e, XmlError::Duplicate { first_line: 2, .. }), "{e}");
        assert_eq!(e.line(), Some(4));
        let bad = "<conf>\n<aircraft name=\"A\"\n  ac_id=\"300\"/>\n</conf>";
        let e = ConfXml::parse(bad, "c.xml").expect_err("id range");
        assert_eq!(e.line(), Some(3));
        let missing = "<conf>\n\n<aircraft name=\"A\"/>\n</conf>";
        let e = ConfXml::parse(missing, "c.xml").expect_err("no id");
        assert!(matches!(e, XmlError::MissingAttribute { .. }));
        assert_eq!(e.line(), Some(3));
    }
}

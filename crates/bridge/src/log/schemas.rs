//! The JSON schemas of every channel, embedded from `crates/bridge/schemas/`.

/// A schema: its name (the MCAP schema name, also the JSON schema's `title`) and its text.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct SchemaDef {
    /// Schema name, e.g. `twinswarm.CopterState` or `foxglove.SceneUpdate`.
    pub name: &'static str,
    /// The JSON schema (`jsonschema` encoding).
    pub json: &'static str,
}

macro_rules! schema {
    ($name:literal) => {
        SchemaDef { name: $name, json: include_str!(concat!("../../schemas/", $name, ".json")) }
    };
}

/// Every schema the logger writes.
pub const SCHEMAS: [SchemaDef; 11] = [
    schema!("twinswarm.CopterState"),
    schema!("twinswarm.CopterSensors"),
    schema!("twinswarm.CopterCommand"),
    schema!("twinswarm.CopterControl"),
    schema!("twinswarm.Event"),
    schema!("twinswarm.BusMessage"),
    schema!("twinswarm.PprzText"),
    schema!("twinswarm.PprzDecoded"),
    schema!("foxglove.FrameTransform"),
    schema!("foxglove.SceneUpdate"),
    schema!("foxglove.Log"),
];

/// The schema with this name.
pub fn schema_for(name: &str) -> Option<&'static SchemaDef> {
    SCHEMAS.iter().find(|s| s.name == name)
}

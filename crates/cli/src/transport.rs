//! The transports' command-line flags, written once: [`ZenohArgs`] (`--zenoh-config`,
//! `--listen`, `--connect`, `--prefix`) and [`IvyArgs`] (`--ivy`, `--ivy-bus`), flattened into
//! every command that speaks Zenoh or Ivy (`run`, `copter`, `replay`), with the one place each
//! becomes what the bridge opens: [`ZenohArgs::config`] and [`IvyArgs::bus`].
//!
//! `--no-bus` stays with each command: what flying or replaying without the bus means is the
//! command's own (`run` may go on Ivy alone, `copter` flies a control run, `replay` serves the
//! live view only). Where a flag's purpose depends on the command (what `--ivy` does, which
//! embedded configuration `--zenoh-config` replaces, where `--prefix` defaults to), the
//! command sets its help text with `#[command(mut_arg(..))]` from the helpers here, so that
//! the shared part (BUS's syntax, the embedded configuration) is written once too.

use std::path::{Path, PathBuf};

use bridge::paparazzi::ivy::BusAddr;
use bridge::zenoh_net::node::{self, DEFAULT_LISTEN};

use crate::BadInput;

/// The Zenoh flags. `L` says whether the command may listen: [`Listen`] (`run`, `replay`) or
/// [`NoListen`] (`copter`, which only connects, as a real copter's link reaches the ground).
#[derive(Debug, Clone, Default, clap::Args)]
pub struct ZenohArgs<L: clap::Args + Endpoints = Listen> {
    /// A full Zenoh configuration file (JSON5), instead of the embedded default.
    #[arg(long, value_name = "FILE.json5", help = zenoh_config_help(ZenohRole::Peer))]
    pub zenoh_config: Option<PathBuf>,
    /// `--listen`, where the command takes it.
    #[command(flatten)]
    pub listen: L,
    /// Zenoh endpoint to connect to (repeatable; overrides the config).
    #[arg(long, value_name = "ENDPOINT")]
    pub connect: Vec<String>,
    /// Key-expression prefix (default: twinswarm/<world name>).
    #[arg(long, value_name = "KEY")]
    pub prefix: Option<String>,
}

/// `--listen`: the endpoints a command that may listen listens on.
#[derive(Debug, Clone, Default, clap::Args)]
pub struct Listen {
    /// Zenoh endpoint to listen on, e.g. tcp/127.0.0.1:7448 (repeatable; overrides the config).
    #[arg(long, value_name = "ENDPOINT")]
    pub listen: Vec<String>,
}

/// No `--listen`: the command only connects.
#[derive(Debug, Clone, Default, clap::Args)]
pub struct NoListen {}

/// The endpoints `--listen` names (none where the command has no `--listen`).
pub trait Endpoints {
    /// `--listen`'s endpoints.
    fn endpoints(&self) -> &[String];
}

impl Endpoints for Listen {
    fn endpoints(&self) -> &[String] {
        &self.listen
    }
}

impl Endpoints for NoListen {
    fn endpoints(&self) -> &[String] {
        &[]
    }
}

/// Which embedded configuration a command starts from without `--zenoh-config`; every one
/// has multicast scouting off.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ZenohRole {
    /// A peer listening on `--listen` (default tcp/127.0.0.1:7447), connecting to `--connect`:
    /// `run`, `replay`.
    Peer,
    /// A shard (`run --shard`): without `--listen`, a client of the router `--connect` names,
    /// so that the shards on one machine do not all listen on the default port; with it, a peer.
    Shard,
    /// A peer that listens nowhere and connects to `--connect` (default tcp/127.0.0.1:7447, a
    /// `run` on this machine): `copter`.
    StandIn,
}

/// The help text of `--zenoh-config` for a command whose embedded configuration is `role`'s.
pub fn zenoh_config_help(role: ZenohRole) -> String {
    let embedded = match role {
        ZenohRole::Peer | ZenohRole::Shard => "peer mode, listen on tcp/127.0.0.1:7447, multicast scouting off",
        ZenohRole::StandIn => "connect to tcp/127.0.0.1:7447, listen nowhere, multicast scouting off",
    };
    format!("A full Zenoh configuration file (JSON5), instead of the embedded default ({embedded})")
}

impl<L: clap::Args + Endpoints> ZenohArgs<L> {
    /// `--listen`'s endpoints (none where the command has no `--listen`).
    pub fn listen(&self) -> &[String] {
        self.listen.endpoints()
    }

    /// Whether the flags say where the other nodes are (a configuration file or an endpoint).
    pub fn names_endpoints(&self) -> bool {
        self.zenoh_config.is_some() || !self.connect.is_empty() || !self.listen().is_empty()
    }

    /// The Zenoh configuration: `--zenoh-config` with `--listen` and `--connect`, when given,
    /// in place of its own endpoints; else `role`'s embedded configuration.
    pub fn config(&self, role: ZenohRole) -> anyhow::Result<zenoh::Config> {
        let (listen, connect) = (self.listen(), self.connect.as_slice());
        if let Some(path) = &self.zenoh_config {
            return config_file(path, listen, connect);
        }
        Ok(match role {
            ZenohRole::Shard if listen.is_empty() => node::config("client", &[], connect)?,
            ZenohRole::Peer | ZenohRole::Shard => node::default_config(listen, connect)?,
            ZenohRole::StandIn if connect.is_empty() => node::client_config(&[DEFAULT_LISTEN.to_owned()])?,
            ZenohRole::StandIn => node::client_config(connect)?,
        })
    }
}

/// A Zenoh configuration file (JSON5), with `listen` and `connect` endpoints, when given, in
/// place of its own.
fn config_file(path: &Path, listen: &[String], connect: &[String]) -> anyhow::Result<zenoh::Config> {
    use anyhow::Context;
    let mut c = zenoh::Config::from_file(path)
        .map_err(|e| anyhow::anyhow!("{e}"))
        .with_context(|| format!("cannot load zenoh config {}", path.display()))?;
    if !listen.is_empty() {
        c.insert_json5("listen/endpoints", &serde_json::to_string(listen)?)
            .map_err(|e| anyhow::anyhow!("--listen: {e}"))?;
    }
    if !connect.is_empty() {
        c.insert_json5("connect/endpoints", &serde_json::to_string(connect)?)
            .map_err(|e| anyhow::anyhow!("--connect: {e}"))?;
    }
    Ok(c)
}

/// The Ivy flags.
#[derive(Debug, Clone, Default, clap::Args)]
pub struct IvyArgs {
    /// Join a Paparazzi Ivy bus; each command says what it does there.
    #[arg(long, value_name = "BUS", num_args = 0..=1, default_missing_value = "", help = ivy_help("Join a Paparazzi Ivy bus"))]
    pub ivy: Option<String>,
    /// The Ivy bus address (same syntax as Paparazzi's `-b`); implies nothing without `--ivy`.
    #[arg(long, value_name = "ADDR:PORT")]
    pub ivy_bus: Option<String>,
}

/// The help text of `--ivy` for a command that does `purpose` on the bus: `purpose`, then BUS's
/// syntax and default.
pub fn ivy_help(purpose: &str) -> String {
    format!(
        "{purpose}. BUS as in Paparazzi (`127.255.255.255:2010`, `127:2010`); default: `--ivy-bus`, else \
         `IVYBUS`, else 127.255.255.255:2010"
    )
}

impl IvyArgs {
    /// The bus `--ivy` joins: its BUS, else `--ivy-bus`, else `IVYBUS`, else
    /// 127.255.255.255:2010; `None` without `--ivy`.
    pub fn bus(&self) -> anyhow::Result<Option<BusAddr>> {
        let Some(b) = &self.ivy else { return Ok(None) };
        let explicit = if b.is_empty() { self.ivy_bus.as_deref() } else { Some(b.as_str()) };
        Ok(Some(BusAddr::from_env_or(explicit).map_err(|e| BadInput(e.into()))?))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::Parser;

    #[derive(Debug, Parser)]
    struct Peer {
        #[command(flatten)]
        zenoh: ZenohArgs,
        #[command(flatten)]
        ivy: IvyArgs,
    }

    #[derive(Debug, Parser)]
    struct Client {
        #[command(flatten)]
        zenoh: ZenohArgs<NoListen>,
    }

    fn json(c: &zenoh::Config, key: &str) -> String {
        c.get_json(key).unwrap().replace(' ', "")
    }

    #[test]
    fn each_role_starts_from_its_embedded_configuration() {
        let peer = Peer::parse_from(["t"]);
        let c = peer.zenoh.config(ZenohRole::Peer).unwrap();
        assert_eq!(json(&c, "mode"), r#""peer""#);
        assert_eq!(json(&c, "listen/endpoints"), format!(r#"["{DEFAULT_LISTEN}"]"#));
        let c = peer.zenoh.config(ZenohRole::Shard).unwrap();
        assert_eq!(json(&c, "mode"), r#""client""#);
        let listening = Peer::parse_from(["t", "--listen", "tcp/127.0.0.1:7448"]);
        let c = listening.zenoh.config(ZenohRole::Shard).unwrap();
        assert_eq!(
            (json(&c, "mode"), json(&c, "listen/endpoints")),
            (r#""peer""#.into(), r#"["tcp/127.0.0.1:7448"]"#.into())
        );
        let c = Client::parse_from(["t"]).zenoh.config(ZenohRole::StandIn).unwrap();
        assert_eq!(json(&c, "listen/endpoints"), "[]");
        assert_eq!(json(&c, "connect/endpoints"), format!(r#"["{DEFAULT_LISTEN}"]"#));
        let c = Client::parse_from(["t", "--connect", "tcp/10.0.0.1:7447"]).zenoh.config(ZenohRole::StandIn).unwrap();
        assert_eq!(json(&c, "connect/endpoints"), r#"["tcp/10.0.0.1:7447"]"#);
    }

    #[test]
    fn a_command_that_only_connects_has_no_listen_flag() {
        assert!(Client::try_parse_from(["t", "--listen", "tcp/127.0.0.1:7448"]).is_err());
        assert!(Client::parse_from(["t", "--connect", "tcp/127.0.0.1:7447"]).zenoh.names_endpoints());
        assert!(!Client::parse_from(["t"]).zenoh.names_endpoints());
    }

    #[test]
    fn ivy_takes_its_bus_then_ivy_bus() {
        assert!(Peer::parse_from(["t"]).ivy.bus().unwrap().is_none());
        let bus = |args: &[&str]| Peer::parse_from(args).ivy.bus().unwrap().unwrap().port;
        assert_eq!(bus(&["t", "--ivy", "127:2011", "--ivy-bus", "127:2012"]), 2011);
        assert_eq!(bus(&["t", "--ivy", "--ivy-bus", "127:2012"]), 2012);
        assert!(Peer::parse_from(["t", "--ivy", "nonsense"]).ivy.bus().is_err());
    }
}

//! The library half of the `twinswarm` binary: the commands that read files a user hands
//! over (`log info|recover`, `plot`), so that fuzz targets (`crates/fuzz`) run exactly the
//! code the binary runs. Everything else stays in the binary.

/// `print!` that ignores a closed stdout (e.g. `twinswarm log info F | head`) instead of
/// panicking.
#[macro_export]
macro_rules! out {
    ($($arg:tt)*) => {{
        use std::io::Write as _;
        let _ = write!(std::io::stdout(), $($arg)*);
    }};
}

/// `println!` that ignores a closed stdout.
#[macro_export]
macro_rules! outln {
    ($($arg:tt)*) => {{
        use std::io::Write as _;
        let _ = writeln!(std::io::stdout(), $($arg)*);
    }};
}

pub mod logcmd;
pub mod plot;
pub mod replay;
pub mod replay_pprz;

/// A Zenoh configuration file (JSON5), with `--listen` and `--connect` endpoints, when given,
/// in place of its own.
pub fn zenoh_config_file(
    path: &std::path::Path,
    listen: &[String],
    connect: &[String],
) -> anyhow::Result<zenoh::Config> {
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

/// An error that is the user's input's fault (exit code 2).
#[derive(Debug)]
pub struct BadInput(pub anyhow::Error);

impl std::fmt::Display for BadInput {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{:#}", self.0)
    }
}
impl std::error::Error for BadInput {}

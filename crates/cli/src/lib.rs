//! The library half of the `twinswarm` binary: the commands that read files a user hands
//! over (`log info|recover`, `plot`, `replay`), so that fuzz targets (`crates/fuzz`) run exactly
//! the code the binary runs, and the transports' flags they share with the binary's commands
//! ([`transport`]). Everything else stays in the binary.

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
pub mod transport;

/// An error that is the user's input's fault (exit code 2).
#[derive(Debug)]
pub struct BadInput(pub anyhow::Error);

impl std::fmt::Display for BadInput {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{:#}", self.0)
    }
}
impl std::error::Error for BadInput {}

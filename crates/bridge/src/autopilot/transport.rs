//! Where the world meets its autopilots: TCP (`HOST:PORT`) or a Unix-domain stream socket
//! (`unix:PATH`, or `unix` alone for a fresh one in a per-run temporary folder). Both carry the
//! same byte stream, the records of protocol v2 (`super`), one per step each way; a Unix socket
//! skips the loopback TCP stack (segments, acknowledgements, timers) on every record, which was
//! most of the world's time per step (docs/paparazzi.md, "Speed").
//!
//! The world binds, NPS connects (`TWINSWARM_FDM=unix:PATH`, `paparazzi/sw/nps_fdm_twinswarm.c`).
//! The socket file is the world's: removed when the run ends, with the folder where the world
//! made one; a stale file left by a killed world is taken over, a live one is an error.

use std::fmt;
use std::io::{self, Read, Write};
use std::net::{Shutdown, SocketAddr, TcpListener, TcpStream};
use std::os::unix::fs::{DirBuilderExt, FileTypeExt};
use std::os::unix::net::{UnixListener, UnixStream};
use std::path::{Path, PathBuf};
use std::str::FromStr;
use std::time::Duration;

/// The longest socket path Linux takes (`sun_path` is 108 bytes with its NUL).
pub const UNIX_PATH_MAX: usize = 107;

/// Where the world listens for its autopilots.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Listen {
    /// TCP, for an autopilot on another machine (or built before Unix sockets: its glue speaks
    /// TCP only).
    Tcp(SocketAddr),
    /// A Unix-domain stream socket at this path; `None`: a fresh one, `fdm.sock` in a new
    /// folder under the system's temporary folder, removed with it at the end of the run.
    Unix(Option<PathBuf>),
}

/// `--autopilot-listen` that is neither form.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error(
    "{0:?} is neither HOST:PORT (an IP address and a port, e.g. 127.0.0.1:7460) nor unix:PATH (a Unix-domain \
     socket; `unix` alone: a fresh one in a temporary folder of this run)"
)]
pub struct BadListen(pub String);

impl FromStr for Listen {
    type Err = BadListen;

    fn from_str(s: &str) -> Result<Self, BadListen> {
        if s == "unix" {
            return Ok(Listen::Unix(None));
        }
        if let Some(path) = s.strip_prefix("unix:") {
            return Ok(Listen::Unix((!path.is_empty()).then(|| PathBuf::from(path))));
        }
        s.parse().map(Listen::Tcp).map_err(|_| BadListen(s.to_owned()))
    }
}

impl fmt::Display for Listen {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Listen::Tcp(a) => write!(f, "{a}"),
            Listen::Unix(Some(p)) => write!(f, "unix:{}", p.display()),
            Listen::Unix(None) => f.write_str("unix"),
        }
    }
}

/// A bound listener ([`super::Autopilots::accept_on`] takes either, e.g. one bound to port 0).
#[derive(Debug)]
pub enum Listener {
    /// TCP.
    Tcp(TcpListener),
    /// A Unix-domain stream socket.
    Unix(UnixListener),
}

impl From<TcpListener> for Listener {
    fn from(l: TcpListener) -> Self {
        Listener::Tcp(l)
    }
}

impl From<UnixListener> for Listener {
    fn from(l: UnixListener) -> Self {
        Listener::Unix(l)
    }
}

impl Listener {
    /// Binds `at`; for a Unix socket also the guard that removes its file (and the folder made
    /// for it) when dropped.
    pub(crate) fn bind(at: &Listen) -> io::Result<(Self, Option<SocketFile>)> {
        match at {
            Listen::Tcp(a) => Ok((Listener::Tcp(TcpListener::bind(a)?), None)),
            Listen::Unix(Some(p)) => {
                let path = std::path::absolute(p)?;
                check_path_len(&path)?;
                take_over_stale(&path)?;
                let l = UnixListener::bind(&path)?;
                Ok((Listener::Unix(l), Some(SocketFile { path, dir: None })))
            }
            Listen::Unix(None) => {
                let dir = fresh_dir()?;
                let path = dir.join("fdm.sock");
                let guard = SocketFile { path: path.clone(), dir: Some(dir) };
                check_path_len(&path)?;
                let l = UnixListener::bind(&path)?;
                Ok((Listener::Unix(l), Some(guard)))
            }
        }
    }

    /// Where it listens, as an autopilot would be told (`TWINSWARM_FDM`).
    pub(crate) fn local(&self) -> io::Result<String> {
        match self {
            Listener::Tcp(l) => Ok(l.local_addr()?.to_string()),
            Listener::Unix(l) => match l.local_addr()?.as_pathname() {
                Some(p) => Ok(format!("unix:{}", p.display())),
                None => Ok("unix:(unnamed)".to_owned()),
            },
        }
    }

    pub(crate) fn set_nonblocking(&self, on: bool) -> io::Result<()> {
        match self {
            Listener::Tcp(l) => l.set_nonblocking(on),
            Listener::Unix(l) => l.set_nonblocking(on),
        }
    }

    /// The next connection and who it is: the peer's address over TCP, the socket's path over a
    /// Unix socket (its peers have no address).
    pub(crate) fn accept(&self) -> io::Result<(Stream, String)> {
        match self {
            Listener::Tcp(l) => {
                let (s, peer) = l.accept()?;
                Ok((Stream::Tcp(s), peer.to_string()))
            }
            Listener::Unix(l) => {
                let (s, _) = l.accept()?;
                let at = l.local_addr().ok().and_then(|a| a.as_pathname().map(|p| p.display().to_string()));
                Ok((Stream::Unix(s), format!("unix:{}", at.unwrap_or_default())))
            }
        }
    }
}

/// One autopilot's connection.
#[derive(Debug)]
pub(crate) enum Stream {
    Tcp(TcpStream),
    Unix(UnixStream),
}

impl Stream {
    /// Sends each record as it is written (TCP: no Nagle delay; a Unix socket has none).
    pub(crate) fn set_nodelay(&self) -> io::Result<()> {
        match self {
            Stream::Tcp(s) => s.set_nodelay(true),
            Stream::Unix(_) => Ok(()),
        }
    }

    pub(crate) fn set_nonblocking(&self, on: bool) -> io::Result<()> {
        match self {
            Stream::Tcp(s) => s.set_nonblocking(on),
            Stream::Unix(s) => s.set_nonblocking(on),
        }
    }

    pub(crate) fn set_read_timeout(&self, t: Option<Duration>) -> io::Result<()> {
        match self {
            Stream::Tcp(s) => s.set_read_timeout(t),
            Stream::Unix(s) => s.set_read_timeout(t),
        }
    }

    pub(crate) fn set_write_timeout(&self, t: Option<Duration>) -> io::Result<()> {
        match self {
            Stream::Tcp(s) => s.set_write_timeout(t),
            Stream::Unix(s) => s.set_write_timeout(t),
        }
    }

    pub(crate) fn shutdown(&self) -> io::Result<()> {
        match self {
            Stream::Tcp(s) => s.shutdown(Shutdown::Both),
            Stream::Unix(s) => s.shutdown(Shutdown::Both),
        }
    }
}

impl Read for &Stream {
    fn read(&mut self, buf: &mut [u8]) -> io::Result<usize> {
        match self {
            Stream::Tcp(s) => (&*s).read(buf),
            Stream::Unix(s) => (&*s).read(buf),
        }
    }
}

impl Write for &Stream {
    fn write(&mut self, buf: &[u8]) -> io::Result<usize> {
        match self {
            Stream::Tcp(s) => (&*s).write(buf),
            Stream::Unix(s) => (&*s).write(buf),
        }
    }

    fn flush(&mut self) -> io::Result<()> {
        Ok(())
    }
}

/// The socket file the world bound, and the folder it made for it: removed when dropped (the
/// end of the run, or a run that could not start).
#[derive(Debug)]
pub(crate) struct SocketFile {
    path: PathBuf,
    dir: Option<PathBuf>,
}

impl Drop for SocketFile {
    fn drop(&mut self) {
        if std::fs::symlink_metadata(&self.path).is_ok_and(|m| m.file_type().is_socket()) {
            let _ = std::fs::remove_file(&self.path);
        }
        if let Some(d) = &self.dir {
            let _ = std::fs::remove_dir(d);
        }
    }
}

fn check_path_len(path: &Path) -> io::Result<()> {
    let n = path.as_os_str().len();
    if n > UNIX_PATH_MAX {
        return Err(io::Error::new(
            io::ErrorKind::InvalidInput,
            format!(
                "the socket path is {n} bytes, a Unix socket's is at most {UNIX_PATH_MAX}: take a shorter one, or \
                 `unix` alone for a fresh one under the temporary folder"
            ),
        ));
    }
    Ok(())
}

/// A file already at `path`: a socket no one listens on (a world that was killed) is removed;
/// one that answers, or anything that is not a socket, is left and is an error.
fn take_over_stale(path: &Path) -> io::Result<()> {
    let Ok(meta) = std::fs::symlink_metadata(path) else { return Ok(()) };
    if !meta.file_type().is_socket() {
        return Err(io::Error::new(io::ErrorKind::AlreadyExists, "a file that is not a socket is there (not removed)"));
    }
    match UnixStream::connect(path) {
        Ok(_) => Err(io::Error::new(io::ErrorKind::AddrInUse, "another process listens on it (another world?)")),
        Err(e) if e.kind() == io::ErrorKind::ConnectionRefused => {
            tracing::info!("{}: a stale socket (no one listens), replaced", path.display());
            std::fs::remove_file(path)
        }
        Err(e) => Err(e),
    }
}

/// A new folder, only the user's, under the system's temporary folder.
fn fresh_dir() -> io::Result<PathBuf> {
    let base = std::env::temp_dir();
    let pid = std::process::id();
    let mut last = None;
    for k in 0..100u32 {
        let nanos = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map_or(0, |d| d.subsec_nanos());
        let dir = base.join(format!("twinswarm-ap.{pid}.{:x}", nanos ^ k.wrapping_mul(0x9e37_79b9)));
        match std::fs::DirBuilder::new().mode(0o700).create(&dir) {
            Ok(()) => return Ok(dir),
            Err(e) if e.kind() == io::ErrorKind::AlreadyExists => last = Some(e),
            Err(e) => return Err(e),
        }
    }
    Err(last.unwrap_or_else(|| io::Error::other("no fresh folder")))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn listen_addresses_parse_and_bad_ones_are_named() {
        assert_eq!("127.0.0.1:7460".parse(), Ok(Listen::Tcp("127.0.0.1:7460".parse().unwrap())));
        assert_eq!("unix".parse(), Ok(Listen::Unix(None)));
        assert_eq!("unix:".parse(), Ok(Listen::Unix(None)));
        assert_eq!("unix:/tmp/x/fdm.sock".parse(), Ok(Listen::Unix(Some("/tmp/x/fdm.sock".into()))));
        let err = "localhost".parse::<Listen>().unwrap_err().to_string();
        assert!(err.contains("\"localhost\" is neither HOST:PORT") && err.contains("unix:PATH"), "{err}");
        assert_eq!(Listen::Unix(Some("/a/b".into())).to_string(), "unix:/a/b");
    }

    #[test]
    fn a_fresh_socket_is_removed_with_its_folder_and_a_stale_one_is_taken_over() {
        let (l, guard) = Listener::bind(&Listen::Unix(None)).unwrap();
        let at = l.local().unwrap();
        let path = PathBuf::from(at.strip_prefix("unix:").unwrap());
        assert!(path.exists() && path.ends_with("fdm.sock"), "{at}");
        let dir = path.parent().unwrap().to_owned();
        // Another world on the same path is refused while this one listens.
        let err = Listener::bind(&Listen::Unix(Some(path.clone()))).unwrap_err();
        assert_eq!(err.kind(), io::ErrorKind::AddrInUse, "{err}");
        drop(l);
        // A world killed without cleaning up leaves its file: the next one takes it over.
        let (again, own) = Listener::bind(&Listen::Unix(Some(path.clone()))).unwrap();
        assert_eq!(again.local().unwrap(), at);
        drop((again, own));
        assert!(!path.exists(), "the explicit path's file is removed at the end");
        assert!(dir.exists(), "a folder the world did not make stays");
        drop(guard);
        assert!(!dir.exists(), "the fresh folder goes with the run");
        // Not a socket: left alone, and said so.
        std::fs::create_dir_all(&dir).unwrap();
        let file = dir.join("plain");
        std::fs::write(&file, "x").unwrap();
        let err = Listener::bind(&Listen::Unix(Some(file.clone()))).unwrap_err().to_string();
        assert!(err.contains("not a socket") && file.exists(), "{err}");
        std::fs::remove_dir_all(&dir).unwrap();
        let long = format!("/tmp/{}", "x".repeat(120));
        let err = Listener::bind(&Listen::Unix(Some(long.into()))).unwrap_err().to_string();
        assert!(err.contains("at most 107"), "{err}");
    }
}

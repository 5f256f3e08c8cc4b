//! The Ivy wire format, version 3, sans I/O: the UDP hello and the TCP lines.
//!
//! **Hello** (UDP, on the bus address): `"<version> <tcp port> <app id> <app name>\n"`
//! (ivy-c `ivy.c` `BroadcastReceive`/`IvyStart`, ivy-python `ivy.py` `IvyServer.start`: the
//! version-3 form carries the app id so an agent recognises its own hello). The app name is
//! the rest of the datagram and may hold spaces.
//!
//! **TCP lines**: `"<type> <ident>\x02<payload>\n"`, one message per line:
//!
//! | type | name | ident | payload |
//! |---|---|---|---|
//! | 0 | Bye | 0 | empty |
//! | 1 | AddRegexp | regex id | the regex |
//! | 2 | Msg | regex id | each captured group followed by `\x03` |
//! | 3 | Error | regex id (or 0) | a message |
//! | 4 | DelRegexp | regex id | empty |
//! | 5 | EndRegexp | 0 | empty |
//! | 6 | StartRegexp | the sender's TCP port | the sender's app name |
//! | 7 | DirectMsg | an id | a text |
//! | 8 | Die | 0 | a message |
//! | 9 | Ping | a ping id | empty |
//! | 10 | Pong | the ping's id | empty |
//!
//! The line delimiter `\n` and the separators `\x02`/`\x03` cannot appear inside a text or
//! a captured group: [`encode_msg`] refuses them rather than send a line peers would split
//! wrongly.

/// The protocol version spoken and accepted.
pub const PROTOCOL_VERSION: u32 = 3;

/// Longest TCP line accepted from a peer, bytes. Longer lines are skipped up to their end and
/// counted; ivy-c grows its buffer without bound, a Paparazzi text is under 2 KiB.
pub const MAX_LINE_BYTES: usize = 64 * 1024;

/// Longest hello datagram accepted, bytes.
pub const MAX_HELLO_BYTES: usize = 1024;

/// Separates the header (`<type> <ident>`) from the payload.
pub const STX: u8 = 0x02;
/// Ends each captured group of a `Msg`.
pub const ETX: u8 = 0x03;

/// An Ivy UDP hello.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Hello {
    /// Protocol version (3 here).
    pub version: u32,
    /// The agent's TCP port.
    pub port: u16,
    /// Unique id of the agent (no spaces).
    pub app_id: String,
    /// Application name (may hold spaces).
    pub app_name: String,
}

/// Why a datagram or a line is not Ivy.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum FrameError {
    /// Not valid UTF-8.
    #[error("not UTF-8")]
    NotUtf8,
    /// Too long.
    #[error("{len_bytes} bytes, the limit is {limit_bytes}")]
    TooLong {
        /// Its length.
        len_bytes: usize,
        /// The limit.
        limit_bytes: usize,
    },
    /// The header is not `<type> <ident>` followed by `\x02`.
    #[error("malformed header: {0:?}")]
    Header(String),
    /// An unknown message type.
    #[error("unknown message type {0}")]
    UnknownType(u32),
    /// A hello that is not `<version> <port> <app id> <app name>`.
    #[error("malformed hello: {0:?}")]
    Hello(String),
}

fn short(s: &str) -> String {
    s.chars().take(80).collect()
}

impl Hello {
    /// Parses a hello datagram. Versions other than 3 parse too (the caller drops them):
    /// version 3 needs the app id, older versions (`"<version> <port>\n"`) do not have one.
    pub fn parse(datagram: &[u8]) -> Result<Hello, FrameError> {
        if datagram.len() > MAX_HELLO_BYTES {
            return Err(FrameError::TooLong { len_bytes: datagram.len(), limit_bytes: MAX_HELLO_BYTES });
        }
        let text = std::str::from_utf8(datagram).map_err(|_| FrameError::NotUtf8)?;
        let text = text.trim_end_matches(['\n', '\r', '\0']);
        let bad = || FrameError::Hello(short(text));
        let mut parts = text.splitn(4, ' ');
        let version: u32 = parts.next().and_then(|v| v.parse().ok()).ok_or_else(bad)?;
        let port: u16 = parts.next().and_then(|v| v.trim().parse().ok()).ok_or_else(bad)?;
        let app_id = parts.next().unwrap_or("").to_owned();
        let app_name = parts.next().unwrap_or("").to_owned();
        if version == PROTOCOL_VERSION && app_id.is_empty() {
            return Err(bad());
        }
        Ok(Hello { version, port, app_id, app_name })
    }

    /// The datagram.
    pub fn encode(&self) -> Vec<u8> {
        format!("{} {} {} {}\n", self.version, self.port, self.app_id, self.app_name).into_bytes()
    }
}

/// One TCP message.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Frame {
    /// The peer leaves.
    Bye,
    /// The peer subscribes `regex` under `id`.
    AddRegexp {
        /// Regex id.
        id: u32,
        /// The regex (PCRE syntax on ivy-c, Python's `re`, Java's on ivy-java).
        regex: String,
    },
    /// A text matched regex `id`: its captured groups.
    Msg {
        /// Regex id (of the receiver).
        id: u32,
        /// Captured groups.
        args: Vec<String>,
    },
    /// An error about regex `id`.
    Error {
        /// Regex id, or 0.
        id: u32,
        /// The message.
        text: String,
    },
    /// The peer unsubscribes regex `id`.
    DelRegexp {
        /// Regex id.
        id: u32,
    },
    /// The peer has sent all its regexes.
    EndRegexp,
    /// The peer introduces itself.
    StartRegexp {
        /// The peer's TCP port.
        port: u16,
        /// The peer's app name.
        app_name: String,
    },
    /// A message to this agent only.
    DirectMsg {
        /// An application-defined id.
        id: u32,
        /// The text.
        text: String,
    },
    /// The peer asks this agent to quit.
    Die {
        /// Ident (0 in practice).
        id: u32,
        /// A reason, possibly empty.
        text: String,
    },
    /// Ping.
    Ping {
        /// Ping id, echoed in the Pong.
        id: u32,
    },
    /// Answer to a Ping.
    Pong {
        /// The ping's id.
        id: u32,
    },
}

impl Frame {
    /// The numeric type.
    pub fn type_code(&self) -> u32 {
        match self {
            Frame::Bye => 0,
            Frame::AddRegexp { .. } => 1,
            Frame::Msg { .. } => 2,
            Frame::Error { .. } => 3,
            Frame::DelRegexp { .. } => 4,
            Frame::EndRegexp => 5,
            Frame::StartRegexp { .. } => 6,
            Frame::DirectMsg { .. } => 7,
            Frame::Die { .. } => 8,
            Frame::Ping { .. } => 9,
            Frame::Pong { .. } => 10,
        }
    }

    /// A short name of the type, for counters and logs.
    pub fn type_name(&self) -> &'static str {
        match self {
            Frame::Bye => "Bye",
            Frame::AddRegexp { .. } => "AddRegexp",
            Frame::Msg { .. } => "Msg",
            Frame::Error { .. } => "Error",
            Frame::DelRegexp { .. } => "DelRegexp",
            Frame::EndRegexp => "EndRegexp",
            Frame::StartRegexp { .. } => "StartRegexp",
            Frame::DirectMsg { .. } => "DirectMsg",
            Frame::Die { .. } => "Die",
            Frame::Ping { .. } => "Ping",
            Frame::Pong { .. } => "Pong",
        }
    }

    /// Parses one line (without its `\n`).
    pub fn parse(line: &[u8]) -> Result<Frame, FrameError> {
        if line.len() > MAX_LINE_BYTES {
            return Err(FrameError::TooLong { len_bytes: line.len(), limit_bytes: MAX_LINE_BYTES });
        }
        // No `\r` is stripped: ivy-c ends a line at `\n` alone, and a payload may end in `\r`
        // (stripping it made such a frame lose one `\r` per hop; found by fuzzing).
        let text = std::str::from_utf8(line).map_err(|_| FrameError::NotUtf8)?;
        let (head, payload) = text.split_once('\x02').ok_or_else(|| FrameError::Header(short(text)))?;
        let (ty, ident) = head.split_once(' ').ok_or_else(|| FrameError::Header(short(head)))?;
        let ty: u32 = ty.parse().map_err(|_| FrameError::Header(short(head)))?;
        let ident: u32 = ident.trim().parse().map_err(|_| FrameError::Header(short(head)))?;
        Ok(match ty {
            0 => Frame::Bye,
            1 => Frame::AddRegexp { id: ident, regex: payload.to_owned() },
            2 => Frame::Msg { id: ident, args: split_args(payload) },
            3 => Frame::Error { id: ident, text: payload.to_owned() },
            4 => Frame::DelRegexp { id: ident },
            5 => Frame::EndRegexp,
            6 => Frame::StartRegexp {
                port: u16::try_from(ident).map_err(|_| FrameError::Header(short(head)))?,
                app_name: payload.to_owned(),
            },
            7 => Frame::DirectMsg { id: ident, text: payload.to_owned() },
            8 => Frame::Die { id: ident, text: payload.to_owned() },
            9 => Frame::Ping { id: ident },
            10 => Frame::Pong { id: ident },
            other => return Err(FrameError::UnknownType(other)),
        })
    }

    /// Appends the line (with its `\n`) to `out`. Texts holding `\n` have that part cut off
    /// (use [`encode_msg`] for checked `Msg`s).
    pub fn encode(&self, out: &mut Vec<u8>) {
        let (ident, payload): (u32, &str) = match self {
            Frame::Bye | Frame::EndRegexp => (0, ""),
            Frame::AddRegexp { id, regex } => (*id, regex),
            Frame::Msg { id, args } => {
                let refs: Vec<&str> = args.iter().map(String::as_str).collect();
                // Checked callers use encode_msg; here bad args are cut like payloads.
                if encode_msg(*id, &refs, out).is_err() {
                    out.extend_from_slice(format!("2 {id}\x02\n").as_bytes());
                }
                return;
            }
            Frame::Error { id, text } | Frame::DirectMsg { id, text } | Frame::Die { id, text } => (*id, text),
            Frame::DelRegexp { id } | Frame::Ping { id } | Frame::Pong { id } => (*id, ""),
            Frame::StartRegexp { port, app_name } => (u32::from(*port), app_name),
        };
        let payload = payload.split('\n').next().unwrap_or("");
        let mut buf = itoa::Buffer::new();
        out.extend_from_slice(buf.format(self.type_code()).as_bytes());
        out.push(b' ');
        out.extend_from_slice(buf.format(ident).as_bytes());
        out.push(STX);
        out.extend_from_slice(payload.as_bytes());
        out.push(b'\n');
    }
}

/// A captured group holds a character the line format cannot carry.
#[derive(Clone, Copy, Debug, PartialEq, Eq, thiserror::Error)]
#[error("a captured group holds a newline, \\x02 or \\x03")]
pub struct UnsendableArg;

/// Appends a `Msg` line for regex `id` with `args` to `out` (ivy-c `MsgSendTo`: every group,
/// including the last, followed by `\x03`). On error nothing is appended.
pub fn encode_msg(id: u32, args: &[&str], out: &mut Vec<u8>) -> Result<(), UnsendableArg> {
    if args.iter().any(|a| a.bytes().any(|b| b == b'\n' || b == STX || b == ETX)) {
        return Err(UnsendableArg);
    }
    let mut buf = itoa::Buffer::new();
    out.extend_from_slice(b"2 ");
    out.extend_from_slice(buf.format(id).as_bytes());
    out.push(STX);
    for a in args {
        out.extend_from_slice(a.as_bytes());
        out.push(ETX);
    }
    out.push(b'\n');
    Ok(())
}

/// Splits a `Msg` payload into its groups: each ends with `\x03`; a last group without its
/// `\x03` (some senders omit it) counts too.
pub fn split_args(payload: &str) -> Vec<String> {
    let mut args: Vec<String> = payload.split('\x03').map(str::to_owned).collect();
    if payload.is_empty() || payload.ends_with('\x03') {
        args.pop();
    }
    args
}

/// Splits a TCP byte stream into lines, sans I/O, with a cap on line length.
///
/// [`LineSplitter::push`] takes what a read returned and yields the complete lines; a line
/// longer than [`MAX_LINE_BYTES`] is dropped up to its end (it yields one
/// [`Line::TooLong`]), so a peer cannot grow this buffer without bound.
#[derive(Debug, Default)]
pub struct LineSplitter {
    buf: Vec<u8>,
    /// Inside an over-long line: skip until its end.
    skipping: bool,
    skipped: usize,
}

/// One item of a byte stream.
#[derive(Debug, PartialEq, Eq)]
pub enum Line<'a> {
    /// A complete line, without its `\n`.
    Complete(&'a [u8]),
    /// A line longer than the cap was dropped; its length.
    TooLong(usize),
}

impl LineSplitter {
    /// Feeds `bytes`; `each` receives every complete line (or over-long line dropped).
    pub fn push(&mut self, mut bytes: &[u8], mut each: impl FnMut(Line<'_>)) {
        while !bytes.is_empty() {
            match bytes.iter().position(|&b| b == b'\n') {
                Some(pos) => {
                    let (head, rest) = (&bytes[..pos], &bytes[pos + 1..]);
                    if self.skipping {
                        each(Line::TooLong(self.skipped + head.len()));
                        self.skipping = false;
                        self.skipped = 0;
                    } else if self.buf.len() + head.len() > MAX_LINE_BYTES {
                        each(Line::TooLong(self.buf.len() + head.len()));
                        self.buf.clear();
                    } else if self.buf.is_empty() {
                        each(Line::Complete(head));
                    } else {
                        self.buf.extend_from_slice(head);
                        each(Line::Complete(&self.buf));
                        self.buf.clear();
                    }
                    bytes = rest;
                }
                None => {
                    if self.skipping {
                        self.skipped += bytes.len();
                    } else if self.buf.len() + bytes.len() > MAX_LINE_BYTES {
                        self.skipping = true;
                        self.skipped = self.buf.len() + bytes.len();
                        self.buf = Vec::new();
                    } else {
                        self.buf.extend_from_slice(bytes);
                    }
                    return;
                }
            }
        }
    }

    /// Bytes held of an incomplete line.
    pub fn pending_bytes(&self) -> usize {
        self.buf.len()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hello_round_trips_and_keeps_spaces_in_the_name() {
        let h = Hello { version: 3, port: 40123, app_id: "abc_1".into(), app_name: "Paparazzi server".into() };
        let bytes = h.encode();
        assert_eq!(bytes, b"3 40123 abc_1 Paparazzi server\n");
        assert_eq!(Hello::parse(&bytes), Ok(h));
        // Version 2 hellos have no id; they parse, the agent drops them.
        assert_eq!(Hello::parse(b"2 4000\n").unwrap().version, 2);
        for bad in [&b""[..], b"3", b"3 x y z", b"3 70000 id n", b"3 1000\n", b"\xff\xfe"] {
            assert!(Hello::parse(bad).is_err(), "{bad:?}");
        }
        assert!(matches!(Hello::parse(&[b'3'; 2000]), Err(FrameError::TooLong { .. })));
    }

    #[test]
    fn frames_round_trip() {
        let frames = [
            Frame::Bye,
            // Found by fuzzing: a payload ending in `\r` lost one per hop.
            Frame::Die { id: 0, text: "bye\r\r".into() },
            Frame::AddRegexp { id: 1, regex: "^(\\S+) ATTIT\r".into() },
            Frame::AddRegexp { id: 7, regex: r"^(\S*) ROTORCRAFT_FP (.*)".into() },
            Frame::Msg { id: 7, args: vec!["5".into(), "1 2 3".into()] },
            Frame::Msg { id: 8, args: vec![] },
            Frame::Msg { id: 9, args: vec!["".into(), "x".into()] },
            Frame::Error { id: 3, text: "bad regex".into() },
            Frame::DelRegexp { id: 7 },
            Frame::EndRegexp,
            Frame::StartRegexp { port: 40000, app_name: "twinswarm".into() },
            Frame::DirectMsg { id: 1, text: "hi".into() },
            Frame::Die { id: 0, text: String::new() },
            Frame::Ping { id: 4 },
            Frame::Pong { id: 4 },
        ];
        for f in frames {
            let mut out = Vec::new();
            f.encode(&mut out);
            assert_eq!(out.last(), Some(&b'\n'));
            assert_eq!(Frame::parse(&out[..out.len() - 1]), Ok(f.clone()), "{out:?}");
        }
        let mut out = Vec::new();
        Frame::Msg { id: 7, args: vec!["5".into(), "1 2".into()] }.encode(&mut out);
        assert_eq!(out, b"2 7\x025\x031 2\x03\n");
    }

    #[test]
    fn msg_args_with_separators_are_refused() {
        let mut out = Vec::new();
        assert_eq!(encode_msg(1, &["a\nb"], &mut out), Err(UnsendableArg));
        assert_eq!(encode_msg(1, &["a\x03b"], &mut out), Err(UnsendableArg));
        assert!(out.is_empty());
        // A last group without its terminator still counts (lenient reading).
        assert_eq!(split_args("a\x03b"), ["a", "b"]);
        assert_eq!(split_args(""), Vec::<String>::new());
    }

    #[test]
    fn bad_lines_are_errors_not_panics() {
        for bad in [&b""[..], b"2", b"2 x\x02", b"99 1\x02", b"\xff 1\x02", b"6 70000\x02n", b"2 -1\x02a"] {
            assert!(Frame::parse(bad).is_err(), "{bad:?}");
        }
    }

    #[test]
    fn splitter_joins_partial_reads_and_drops_overlong_lines() {
        let mut s = LineSplitter::default();
        let mut got: Vec<String> = Vec::new();
        let mut rec = |l: Line<'_>| match l {
            Line::Complete(b) => got.push(String::from_utf8_lossy(b).into_owned()),
            Line::TooLong(n) => got.push(format!("<{n}>")),
        };
        s.push(b"9 1\x02\n5 0", &mut rec);
        s.push(b"\x02\n", &mut rec);
        let big = vec![b'a'; MAX_LINE_BYTES + 10];
        s.push(&big, &mut rec);
        s.push(&big, &mut rec);
        assert!(s.pending_bytes() == 0);
        s.push(b"tail\n9 2\x02\n", &mut rec);
        assert_eq!(got, ["9 1\x02", "5 0\x02", format!("<{}>", 2 * big.len() + 4).as_str(), "9 2\x02"]);
    }
}

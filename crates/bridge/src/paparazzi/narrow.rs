//! Narrowing of Ivy regexes: from a regex, what the sender and the name of every text it can
//! match look like (exact, a glob, or anything).
//!
//! [`narrow`] walks the regex's HIR (`regex-syntax`, same syntax as the
//! `regex` crate) from a leading `^`/`\A` anchor and follows the literal
//! parts through the header: sender chunk, the run of spaces, name chunk.
//! Each chunk becomes exact (`5`, `ATTITUDE`), a glob with in-chunk
//! wildcards (`ROTORCRAFT_FP$*` for `^5 ROTORCRAFT_FP`, which also
//! matches `ROTORCRAFT_FP_MIN`), or anything. When nothing can be determined (no
//! anchor, multi-line `(?m)^`, a leading `.*`, ...) both chunks are anything.
//!
//! The regex bus ([`crate::paparazzi::bus`]) indexes its bindings by the narrowed name, and
//! the Zenoh side ([`crate::zenoh_net::keyexpr`]) turns a narrowing into the key expression it
//! subscribes.
//!
//! **Invariant:** the analysis only ever widens. Every construct it does not
//! understand turns the rest of the header into wildcards, so for every text
//! `t` with a key, `regex.is_match(t)` implies that the narrowed expression
//! matches `key_for_text(prefix, t)`. The tests check this on a corpus of
//! messages and patterns, against Zenoh's own key-expression matching.

use regex_syntax::hir::{Class, Hir, HirKind, Look};

/// Characters that may not appear in a key chunk (Zenoh's special characters): a regex
/// literal holding one widens to a wildcard.
pub const KEY_SPECIAL: [char; 5] = ['/', '*', '$', '?', '#'];

/// What is known about one chunk (sender or name) of every matching text.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum ChunkPattern {
    /// Exactly this text.
    Exact(String),
    /// Literal pieces with `$*` wildcards between/around them (at least one
    /// wildcard and one literal).
    Glob(Vec<GlobPiece>),
    /// Anything.
    Any,
}

/// A piece of a [`ChunkPattern::Glob`].
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum GlobPiece {
    /// Literal text.
    Lit(String),
    /// Any run of characters within the chunk (`$*`).
    Star,
}

impl ChunkPattern {
    fn from_pieces(pieces: &[GlobPiece]) -> ChunkPattern {
        let has_star = pieces.contains(&GlobPiece::Star);
        let has_lit = pieces.iter().any(|p| matches!(p, GlobPiece::Lit(_)));
        match (has_star, has_lit) {
            (false, true) => ChunkPattern::Exact(
                pieces
                    .iter()
                    .filter_map(|p| match p {
                        GlobPiece::Lit(s) => Some(s.as_str()),
                        GlobPiece::Star => None,
                    })
                    .collect(),
            ),
            (true, true) => ChunkPattern::Glob(pieces.to_vec()),
            _ => ChunkPattern::Any,
        }
    }

    /// The exact text, if known.
    pub fn exact(&self) -> Option<&str> {
        match self {
            ChunkPattern::Exact(s) => Some(s),
            _ => None,
        }
    }

    /// Key-expression form of the chunk.
    pub fn to_chunk(&self) -> String {
        match self {
            ChunkPattern::Exact(s) => s.clone(),
            ChunkPattern::Any => "*".to_owned(),
            ChunkPattern::Glob(pieces) => pieces
                .iter()
                .map(|p| match p {
                    GlobPiece::Lit(s) => s.as_str(),
                    GlobPiece::Star => "$*",
                })
                .collect(),
        }
    }
}

/// Result of narrowing a regex: what every matching text's sender and name
/// chunks look like.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Narrowing {
    /// Sender chunk.
    pub sender: ChunkPattern,
    /// Name chunk.
    pub name: ChunkPattern,
}

impl Narrowing {
    /// Nothing known.
    pub fn any() -> Narrowing {
        Narrowing { sender: ChunkPattern::Any, name: ChunkPattern::Any }
    }
}

fn flatten<'h>(hir: &'h Hir, out: &mut Vec<&'h Hir>) {
    match hir.kind() {
        HirKind::Concat(items) => items.iter().for_each(|h| flatten(h, out)),
        HirKind::Capture(c) => flatten(&c.sub, out),
        _ => out.push(hir),
    }
}

fn class_has_space(c: &Class) -> bool {
    match c {
        Class::Unicode(u) => u.ranges().iter().any(|r| r.start() <= ' ' && ' ' <= r.end()),
        Class::Bytes(b) => b.ranges().iter().any(|r| r.start() <= b' ' && b' ' <= r.end()),
    }
}

fn class_only_space(c: &Class) -> bool {
    match c {
        Class::Unicode(u) => u.ranges().iter().all(|r| r.start() == ' ' && r.end() == ' '),
        Class::Bytes(b) => b.ranges().iter().all(|r| r.start() == b' ' && r.end() == b' '),
    }
}

/// Every character any match of `h` consumes is a space.
fn only_spaces(h: &Hir) -> bool {
    match h.kind() {
        HirKind::Empty | HirKind::Look(_) => true,
        HirKind::Literal(l) => l.0.iter().all(|b| *b == b' '),
        HirKind::Class(c) => class_only_space(c),
        HirKind::Repetition(r) => only_spaces(&r.sub),
        HirKind::Capture(c) => only_spaces(&c.sub),
        HirKind::Concat(v) | HirKind::Alternation(v) => v.iter().all(only_spaces),
    }
}

/// No match of `h` consumes a space.
fn never_spaces(h: &Hir) -> bool {
    match h.kind() {
        HirKind::Empty | HirKind::Look(_) => true,
        HirKind::Literal(l) => !l.0.contains(&b' '),
        HirKind::Class(c) => !class_has_space(c),
        HirKind::Repetition(r) => never_spaces(&r.sub),
        HirKind::Capture(c) => never_spaces(&c.sub),
        HirKind::Concat(v) | HirKind::Alternation(v) => v.iter().all(never_spaces),
    }
}

fn min_len(h: &Hir) -> usize {
    h.properties().minimum_len().unwrap_or(0)
}

/// Every match of `h` either starts with a space or is at the end of the
/// text (so a chunk that precedes it ends there).
fn starts_with_space_or_end(h: &Hir) -> bool {
    match h.kind() {
        HirKind::Literal(l) => l.0.first() == Some(&b' '),
        HirKind::Look(Look::End) => true,
        HirKind::Class(c) => class_only_space(c),
        HirKind::Repetition(r) => r.min >= 1 && starts_with_space_or_end(&r.sub),
        HirKind::Capture(c) => starts_with_space_or_end(&c.sub),
        HirKind::Alternation(v) => v.iter().all(starts_with_space_or_end),
        HirKind::Concat(v) => match v.first() {
            Some(first) => starts_with_space_or_end(first),
            None => false,
        },
        HirKind::Empty | HirKind::Look(_) => false,
    }
}

#[derive(Clone, Copy, PartialEq, Eq)]
enum Phase {
    Sender,
    Separator,
    Name,
}

struct Walker {
    phase: Phase,
    cur: Vec<GlobPiece>,
    sender: ChunkPattern,
}

impl Walker {
    fn push_char(&mut self, c: char) {
        if KEY_SPECIAL.contains(&c) {
            // Texts with such characters have no key; widening is safe.
            self.push_star();
            return;
        }
        match self.cur.last_mut() {
            Some(GlobPiece::Lit(s)) => s.push(c),
            _ => self.cur.push(GlobPiece::Lit(c.to_string())),
        }
    }

    fn push_star(&mut self) {
        if self.cur.last() != Some(&GlobPiece::Star) {
            self.cur.push(GlobPiece::Star);
        }
    }

    /// Current chunk widened by a trailing wildcard, then everything after
    /// it unknown.
    fn give_up(mut self) -> Narrowing {
        match self.phase {
            Phase::Sender => {
                self.push_star();
                Narrowing { sender: ChunkPattern::from_pieces(&self.cur), name: ChunkPattern::Any }
            }
            Phase::Separator => Narrowing { sender: self.sender, name: ChunkPattern::Any },
            Phase::Name => {
                self.push_star();
                Narrowing { sender: self.sender, name: ChunkPattern::from_pieces(&self.cur) }
            }
        }
    }

    /// The current chunk ends here (a space or the end of text follows).
    /// Returns the final result when the name chunk is complete.
    fn end_chunk(&mut self) -> Result<Option<Narrowing>, ()> {
        match self.phase {
            Phase::Sender => {
                if self.cur.is_empty() {
                    return Err(()); // empty sender: no key
                }
                self.sender = ChunkPattern::from_pieces(&self.cur);
                self.cur.clear();
                self.phase = Phase::Separator;
                Ok(None)
            }
            Phase::Separator => Ok(None),
            Phase::Name => {
                Ok(Some(Narrowing { sender: self.sender.clone(), name: ChunkPattern::from_pieces(&self.cur) }))
            }
        }
    }
}

/// Narrows an already parsed HIR (see module docs).
pub fn narrow_hir(hir: &Hir) -> Narrowing {
    let mut items = Vec::new();
    flatten(hir, &mut items);
    let mut iter = items.into_iter();
    match iter.next().map(Hir::kind) {
        Some(HirKind::Look(Look::Start)) => {}
        _ => return Narrowing::any(),
    }
    let mut w = Walker { phase: Phase::Sender, cur: Vec::new(), sender: ChunkPattern::Any };
    for item in iter {
        match item.kind() {
            HirKind::Empty => {}
            HirKind::Literal(lit) => {
                let Ok(text) = std::str::from_utf8(&lit.0) else {
                    return w.give_up();
                };
                for c in text.chars() {
                    if c == ' ' {
                        match w.end_chunk() {
                            Ok(Some(done)) => return done,
                            Ok(None) => {}
                            Err(()) => return Narrowing::any(),
                        }
                    } else {
                        if w.phase == Phase::Separator {
                            w.phase = Phase::Name;
                        }
                        w.push_char(c);
                    }
                }
            }
            HirKind::Look(Look::End) => {
                return match w.phase {
                    // The text ends inside the header: it has no key, and
                    // nothing needs to be received.
                    Phase::Sender | Phase::Separator => Narrowing::any(),
                    Phase::Name => match w.end_chunk() {
                        Ok(Some(done)) => done,
                        _ => Narrowing::any(),
                    },
                };
            }
            // Other zero-width assertions only restrict matches; ignoring
            // them widens.
            HirKind::Look(_) => {}
            _ if only_spaces(item) => {
                if min_len(item) >= 1 {
                    match w.end_chunk() {
                        Ok(Some(done)) => return done,
                        Ok(None) => {}
                        Err(()) => return Narrowing::any(),
                    }
                } else if w.phase != Phase::Separator {
                    return w.give_up();
                }
            }
            _ if never_spaces(item) => {
                if w.phase == Phase::Separator {
                    w.phase = Phase::Name;
                }
                w.push_star();
            }
            _ if starts_with_space_or_end(item) => {
                return match w.phase {
                    Phase::Name => match w.end_chunk() {
                        Ok(Some(done)) => done,
                        _ => Narrowing::any(),
                    },
                    Phase::Sender => match w.end_chunk() {
                        Ok(_) => Narrowing { sender: w.sender, name: ChunkPattern::Any },
                        Err(()) => Narrowing::any(),
                    },
                    Phase::Separator => w.give_up(),
                };
            }
            _ => return w.give_up(),
        }
    }
    // The pattern ends: whatever follows in the text is unconstrained.
    w.give_up()
}

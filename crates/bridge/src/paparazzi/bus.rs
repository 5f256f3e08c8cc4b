//! An Ivy-style message bus core, independent of any transport.
//!
//! Like Ivy's `IvyBindMsg`, a subscriber binds a regular expression and a
//! handler; every dispatched text the regex matches is delivered with the
//! regex's capture groups. [`Bus::bind_from`] additionally restricts a
//! binding to one aircraft (the text's sender token must be its `ac_id`),
//! which is what the original Java bridge's `subscribeToIdMessage` did.
//!
//! # Semantics
//!
//! * Regexes use the `regex` crate's syntax and are searched anywhere in
//!   the text, as in Ivy; anchor with `^` to match from the start. Matching
//!   runs in time linear in the text, so hostile patterns cannot stall the
//!   bus; compiled patterns are capped at [`REGEX_SIZE_LIMIT_BYTES`] and the
//!   pattern text at [`MAX_PATTERN_LEN_BYTES`].
//! * Captures are delivered as Ivy does: groups 1..n in order, a group that
//!   did not participate is delivered as the empty string.
//! * Handlers run in bind order ([`BindId`] order), synchronously inside
//!   [`Bus::dispatch`].
//! * **Unbinding from a handler:** a handler receives a [`Control`] and may
//!   call [`Control::unbind_self`] or [`Control::unbind`]; the effect is
//!   immediate for the rest of the current dispatch (an unbound binding that
//!   has not run yet in this dispatch does not run). Outside handlers, use
//!   [`Bus::unbind`]. Binding new handlers from inside a handler is not
//!   supported (the bus is mutably borrowed); collect them and bind after
//!   `dispatch` returns.
//!
//! # Speed
//!
//! Each binding's regex is narrowed once at bind time
//! ([`narrow`]). Bindings whose message name is known
//! exactly are indexed by name, so a text is only matched against the
//! regexes that can match its name plus the few whose name is not known;
//! bindings with an exact sender (or [`Bus::bind_from`]) are skipped by a
//! string comparison before any regex runs. The same narrowing gives the
//! Zenoh key expressions to subscribe ([`crate::zenoh_net::keyexpr::bus_key_exprs`]).

use std::collections::HashMap;

use regex::{CaptureLocations, Regex, RegexBuilder};

use crate::ids::AcId;
use crate::paparazzi::codec::split_header;
use crate::paparazzi::narrow::{ChunkPattern, Narrowing, narrow_hir};

/// Maximum compiled size of one binding's regex (`RegexBuilder::size_limit`).
pub const REGEX_SIZE_LIMIT_BYTES: usize = 1 << 20;

/// Maximum length of a pattern's text.
pub const MAX_PATTERN_LEN_BYTES: usize = 4096;

/// Parses `pattern` with `regex-syntax` and narrows it ([`crate::paparazzi::narrow`]).
pub fn narrow(pattern: &str) -> Result<Narrowing, BusError> {
    let hir = regex_syntax::ParserBuilder::new()
        .build()
        .parse(pattern)
        .map_err(|e| BusError::BadPattern { pattern: pattern.chars().take(200).collect(), message: e.to_string() })?;
    Ok(narrow_hir(&hir))
}

/// Errors of the bus and of key handling.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum BusError {
    /// The pattern does not parse.
    #[error("bad regex `{pattern}`: {message}")]
    BadPattern {
        /// The pattern (first 200 characters).
        pattern: String,
        /// The parser's message.
        message: String,
    },
    /// The pattern text is longer than [`MAX_PATTERN_LEN_BYTES`].
    #[error("regex is {len_bytes} bytes long, the limit is {limit_bytes}")]
    PatternTooLong {
        /// Length of the pattern.
        len_bytes: usize,
        /// The limit.
        limit_bytes: usize,
    },
    /// The compiled pattern exceeds [`REGEX_SIZE_LIMIT_BYTES`].
    #[error("regex `{pattern}` compiles to more than {limit_bytes} bytes")]
    PatternTooLarge {
        /// The pattern (first 200 characters).
        pattern: String,
        /// The limit.
        limit_bytes: usize,
    },
    /// A sender or name that cannot be a key chunk.
    #[error("`{chunk}` cannot be a key chunk (empty, whitespace or one of / * $ ? #)")]
    InvalidKeyChunk {
        /// The offending chunk.
        chunk: String,
    },
    /// An Ivy text without sender and name.
    #[error("Ivy text has no `<sender> <NAME>` header: `{text}`")]
    NoHeader {
        /// The text (first 80 characters).
        text: String,
    },
}

/// Identifies a binding. Ids increase with every bind and are never reused.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct BindId(pub u64);

/// What a handler receives for one matching text.
#[derive(Debug)]
pub struct Delivery<'a> {
    /// The binding that matched.
    pub bind_id: BindId,
    /// The key the text arrived on (as given to [`Bus::dispatch`]).
    pub key: &'a str,
    /// The whole text.
    pub text: &'a str,
    /// Capture groups 1..n (empty string for groups that did not match).
    pub captures: &'a [&'a str],
}

/// Lets a handler change the bus while it is being dispatched.
#[derive(Debug)]
pub struct Control {
    current: BindId,
    unbinds: Vec<BindId>,
}

impl Control {
    /// Unbinds the binding whose handler is running.
    pub fn unbind_self(&mut self) {
        self.unbinds.push(self.current);
    }

    /// Unbinds `id` (takes effect for the rest of this dispatch).
    pub fn unbind(&mut self, id: BindId) {
        self.unbinds.push(id);
    }

    /// The binding whose handler is running.
    pub fn current(&self) -> BindId {
        self.current
    }
}

/// A handler: called with the delivery and a [`Control`].
pub type Handler = Box<dyn FnMut(&Delivery<'_>, &mut Control) + Send>;

struct Binding {
    regex: Regex,
    locs: CaptureLocations,
    /// Required sender token (from `bind_from` or an exact narrowed sender).
    sender: Option<String>,
    /// Name the binding is indexed under, if exact.
    name: Option<String>,
    narrowing: Narrowing,
    handler: Handler,
}

/// Public description of a binding.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct BindInfo {
    /// Id.
    pub id: BindId,
    /// Pattern text.
    pub pattern: String,
    /// Narrowing of the pattern (sender forced for `bind_from`).
    pub narrowing: Narrowing,
}

/// The bus: bindings and dispatch. `Send`, not `Sync`; wrap in a mutex or
/// own it from one task.
#[derive(Default)]
pub struct Bus {
    next_id: u64,
    /// Bindings by id (BTreeMap would do; a sorted Vec keeps dispatch cheap).
    bindings: Vec<(BindId, Option<Binding>)>,
    by_name: HashMap<String, Vec<BindId>>,
    /// Bindings whose name is not known exactly, in id order.
    unnamed: Vec<BindId>,
    live: usize,
}

impl std::fmt::Debug for Bus {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Bus").field("bindings", &self.live).finish()
    }
}

/// Compiles `pattern` with the bus's limits, and narrows it.
pub(crate) fn compile(pattern: &str) -> Result<(Regex, Narrowing), BusError> {
    if pattern.len() > MAX_PATTERN_LEN_BYTES {
        return Err(BusError::PatternTooLong { len_bytes: pattern.len(), limit_bytes: MAX_PATTERN_LEN_BYTES });
    }
    let short = || pattern.chars().take(200).collect::<String>();
    let regex = RegexBuilder::new(pattern)
        .size_limit(REGEX_SIZE_LIMIT_BYTES)
        .dfa_size_limit(REGEX_SIZE_LIMIT_BYTES)
        .build()
        .map_err(|e| match e {
            regex::Error::CompiledTooBig(limit) => BusError::PatternTooLarge { pattern: short(), limit_bytes: limit },
            other => BusError::BadPattern { pattern: short(), message: other.to_string() },
        })?;
    // Same syntax as the regex crate; if the HIR parser disagreed we would
    // not narrow at all, which is always safe.
    let narrowing = regex_syntax::ParserBuilder::new()
        .build()
        .parse(pattern)
        .map(|hir| narrow_hir(&hir))
        .unwrap_or_else(|_| Narrowing::any());
    Ok((regex, narrowing))
}

/// The sender token of a text: everything before the first space.
fn sender_token(text: &str) -> &str {
    text.split_once(' ').map(|(s, _)| s).unwrap_or(text)
}

impl Bus {
    /// An empty bus.
    pub fn new() -> Bus {
        Bus::default()
    }

    /// Binds `pattern`; `handler` receives every dispatched text it matches.
    pub fn bind<F>(&mut self, pattern: &str, handler: F) -> Result<BindId, BusError>
    where
        F: FnMut(&Delivery<'_>, &mut Control) + Send + 'static,
    {
        self.bind_inner(None, pattern, Box::new(handler))
    }

    /// Like [`Bus::bind`], but only texts whose sender is `ac_id`.
    pub fn bind_from<F>(&mut self, ac_id: AcId, pattern: &str, handler: F) -> Result<BindId, BusError>
    where
        F: FnMut(&Delivery<'_>, &mut Control) + Send + 'static,
    {
        self.bind_inner(Some(ac_id), pattern, Box::new(handler))
    }

    fn bind_inner(&mut self, from: Option<AcId>, pattern: &str, handler: Handler) -> Result<BindId, BusError> {
        let (regex, mut narrowing) = compile(pattern)?;
        if let Some(ac_id) = from {
            narrowing.sender = ChunkPattern::Exact(ac_id.to_string());
        }
        let id = BindId(self.next_id);
        self.next_id += 1;
        let name = narrowing.name.exact().map(str::to_owned);
        match &name {
            Some(n) => self.by_name.entry(n.clone()).or_default().push(id),
            None => self.unnamed.push(id),
        }
        let locs = regex.capture_locations();
        self.bindings.push((
            id,
            Some(Binding {
                regex,
                locs,
                sender: narrowing.sender.exact().map(str::to_owned),
                name,
                narrowing,
                handler,
            }),
        ));
        self.live += 1;
        Ok(id)
    }

    fn slot(&self, id: BindId) -> Option<usize> {
        self.bindings.binary_search_by_key(&id, |(i, _)| *i).ok()
    }

    /// Removes a binding. Returns `false` if it was not bound.
    pub fn unbind(&mut self, id: BindId) -> bool {
        let Some(idx) = self.slot(id) else {
            return false;
        };
        let Some(binding) = self.bindings[idx].1.take() else {
            return false;
        };
        self.live -= 1;
        self.forget(id, binding.name.as_deref());
        true
    }

    /// Removes `id` from the name indexes and compacts the table.
    fn forget(&mut self, id: BindId, name: Option<&str>) {
        let list = match name {
            Some(n) => self.by_name.get_mut(n),
            None => Some(&mut self.unnamed),
        };
        if let Some(list) = list
            && let Ok(pos) = list.binary_search(&id)
        {
            list.remove(pos);
        }
        if let Some(n) = name
            && self.by_name.get(n).is_some_and(Vec::is_empty)
        {
            self.by_name.remove(n);
        }
        // Compact occasionally so the id table does not grow without bound.
        if self.bindings.len() > 64 && self.live * 2 < self.bindings.len() {
            self.bindings.retain(|(_, b)| b.is_some());
        }
    }

    /// Number of live bindings.
    pub fn len(&self) -> usize {
        self.live
    }

    /// Whether there is no binding.
    pub fn is_empty(&self) -> bool {
        self.live == 0
    }

    /// Live bindings in id order.
    pub fn bindings(&self) -> Vec<BindInfo> {
        self.bindings
            .iter()
            .filter_map(|(id, b)| {
                b.as_ref().map(|b| BindInfo {
                    id: *id,
                    pattern: b.regex.as_str().to_owned(),
                    narrowing: b.narrowing.clone(),
                })
            })
            .collect()
    }

    /// Delivers `text` to binding `id` alone, if its regex matches (a transport that already
    /// knows which binding a text is for, such as the Ivy wire protocol, whose peers match
    /// sender-side). Returns whether the handler ran.
    pub fn deliver_to(&mut self, id: BindId, key: &str, text: &str) -> bool {
        let Some(idx) = self.slot(id) else { return false };
        let Some(b) = self.bindings[idx].1.as_mut() else { return false };
        if b.regex.captures_read(&mut b.locs, text).is_none() {
            return false;
        }
        let captures: Vec<&str> =
            (1..b.locs.len()).map(|g| b.locs.get(g).map(|(s, e)| &text[s..e]).unwrap_or("")).collect();
        let mut ctl = Control { current: id, unbinds: Vec::new() };
        (b.handler)(&Delivery { bind_id: id, key, text, captures: &captures }, &mut ctl);
        for u in ctl.unbinds {
            self.unbind(u);
        }
        true
    }

    /// Delivers `text` (which arrived on `key`) to every binding whose
    /// regex matches it. Returns the number of handler calls.
    pub fn dispatch(&mut self, key: &str, text: &str) -> usize {
        self.dispatch_among(key, text, |_| true)
    }

    /// Like [`Bus::dispatch`], but only to the bindings `among` accepts (a transport with one
    /// subscription per key expression delivers each sample to the bindings of that
    /// subscription only, so that overlapping subscriptions do not deliver a text twice).
    pub fn dispatch_among(&mut self, key: &str, text: &str, among: impl Fn(BindId) -> bool) -> usize {
        let sender = sender_token(text);
        let named: &[BindId] = match split_header(text) {
            Some((_, name, _)) => self.by_name.get(name).map(Vec::as_slice).unwrap_or(&[]),
            // No name: no binding with an exact name can match.
            None => &[],
        };
        let unnamed: &[BindId] = &self.unnamed;
        let bindings = &mut self.bindings;
        let mut removed: Vec<(BindId, Option<String>)> = Vec::new();
        let mut captures: Vec<&str> = Vec::new();
        let mut delivered = 0;
        // Merge the two id-sorted candidate lists to keep bind order.
        let (mut i, mut j) = (0, 0);
        while i < named.len() || j < unnamed.len() {
            let id = match (named.get(i), unnamed.get(j)) {
                (Some(a), Some(b)) if a < b => {
                    i += 1;
                    *a
                }
                (Some(a), None) => {
                    i += 1;
                    *a
                }
                (_, Some(b)) => {
                    j += 1;
                    *b
                }
                (None, None) => break,
            };
            if !among(id) {
                continue;
            }
            let Ok(idx) = bindings.binary_search_by_key(&id, |(i, _)| *i) else {
                continue;
            };
            let Some(b) = bindings[idx].1.as_mut() else {
                continue;
            };
            if let Some(s) = &b.sender
                && s != sender
            {
                continue;
            }
            if b.regex.captures_read(&mut b.locs, text).is_none() {
                continue;
            }
            captures.clear();
            for g in 1..b.locs.len() {
                captures.push(b.locs.get(g).map(|(s, e)| &text[s..e]).unwrap_or(""));
            }
            let mut ctl = Control { current: id, unbinds: Vec::new() };
            (b.handler)(&Delivery { bind_id: id, key, text, captures: &captures }, &mut ctl);
            delivered += 1;
            for u in ctl.unbinds {
                if let Ok(k) = bindings.binary_search_by_key(&u, |(i, _)| *i)
                    && let Some(dead) = bindings[k].1.take()
                {
                    // Dead for the rest of this dispatch; the indexes are
                    // cleaned once they are no longer borrowed.
                    removed.push((u, dead.name));
                }
            }
        }
        self.live -= removed.len();
        for (id, name) in removed {
            self.forget(id, name.as_deref());
        }
        delivered
    }
}

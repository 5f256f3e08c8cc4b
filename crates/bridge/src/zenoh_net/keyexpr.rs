//! Zenoh key expressions for Paparazzi texts.
//!
//! An Ivy text `<sender> <NAME> ...` is published under
//! `<prefix>/pprz/<sender>/<NAME>` ([`key_for`], [`key_for_text`]). The
//! header split is [`crate::paparazzi::codec::split_header`]: the sender is everything
//! before the first space, the name the next run of non-space characters.
//! Senders and names that cannot be a key chunk (empty, or containing
//! whitespace or any of `/ * $ ? #`) have no key.
//!
//! A regex's [`Narrowing`] becomes the narrowest key expression that still receives every
//! text it can match ([`key_expr`], [`narrow_key_expr`]): exact chunks stay, globs use Zenoh's
//! in-chunk wildcard `$*`, unknown chunks are `*`, and nothing known at all is
//! `<prefix>/pprz/**`.

use crate::paparazzi::bus::{Bus, BusError, narrow};
use crate::paparazzi::codec::split_header;
use crate::paparazzi::narrow::{ChunkPattern, KEY_SPECIAL, Narrowing};

/// Whether `s` can be used verbatim as one key-expression chunk.
pub fn is_valid_chunk(s: &str) -> bool {
    !s.is_empty() && !s.contains(KEY_SPECIAL) && !s.chars().any(|c| c.is_whitespace() || c.is_control())
}

/// `<prefix>/pprz/<sender>/<name>`, or an error if a part is not a valid
/// chunk.
pub fn key_for(prefix: &str, sender: &str, name: &str) -> Result<String, BusError> {
    for chunk in [sender, name] {
        if !is_valid_chunk(chunk) {
            return Err(BusError::InvalidKeyChunk { chunk: chunk.to_owned() });
        }
    }
    Ok(format!("{prefix}/pprz/{sender}/{name}"))
}

/// The key of an Ivy text (see the module docs), or an error if the text
/// has no usable header.
pub fn key_for_text(prefix: &str, text: &str) -> Result<String, BusError> {
    let (sender, name, _) =
        split_header(text).ok_or_else(|| BusError::NoHeader { text: text.chars().take(80).collect() })?;
    key_for(prefix, sender, name)
}

/// The key expression of `n` under `prefix`: `<prefix>/pprz/<s>/<n>`, or
/// `<prefix>/pprz/**` when neither chunk is known.
pub fn key_expr(n: &Narrowing, prefix: &str) -> String {
    if n.sender == ChunkPattern::Any && n.name == ChunkPattern::Any {
        format!("{prefix}/pprz/**")
    } else {
        format!("{prefix}/pprz/{}/{}", n.sender.to_chunk(), n.name.to_chunk())
    }
}

/// The narrowest key expression under `prefix` for `pattern`, e.g.
/// `^(\S*) ATTITUDE (.*)` → `<prefix>/pprz/*/ATTITUDE`.
pub fn narrow_key_expr(prefix: &str, pattern: &str) -> Result<String, BusError> {
    Ok(key_expr(&narrow(pattern)?, prefix))
}

/// The key expressions (under `prefix`) that together receive every text some binding of
/// `bus` can match; sorted and deduplicated.
pub fn bus_key_exprs(bus: &Bus, prefix: &str) -> Vec<String> {
    let mut v: Vec<String> = bus.bindings().iter().map(|b| key_expr(&b.narrowing, prefix)).collect();
    v.sort();
    v.dedup();
    v
}

/// Reference matcher for the subset of Zenoh key expressions produced here:
/// `*` (one chunk), `**` (any number of chunks, including none) and `$*`
/// (any run of characters inside a chunk, including none).
///
/// Intended for tests and diagnostics; the Zenoh layer uses Zenoh's own.
pub fn key_expr_matches(expr: &str, key: &str) -> bool {
    let e: Vec<&str> = expr.split('/').collect();
    let k: Vec<&str> = key.split('/').collect();
    // dp[i][j]: e[i..] matches k[j..]
    let mut dp = vec![vec![false; k.len() + 1]; e.len() + 1];
    dp[e.len()][k.len()] = true;
    for i in (0..e.len()).rev() {
        for j in (0..=k.len()).rev() {
            dp[i][j] = if e[i] == "**" {
                dp[i + 1][j] || (j < k.len() && dp[i][j + 1])
            } else {
                j < k.len() && chunk_matches(e[i], k[j]) && dp[i + 1][j + 1]
            };
        }
    }
    dp[0][0]
}

fn chunk_matches(pattern: &str, chunk: &str) -> bool {
    if pattern == "*" {
        return !chunk.is_empty();
    }
    let pieces: Vec<&str> = pattern.split("$*").collect();
    if pieces.len() == 1 {
        return pattern == chunk;
    }
    let (first, rest) = (pieces[0], &pieces[1..]);
    let Some(mut remaining) = chunk.strip_prefix(first) else {
        return false;
    };
    let last = rest[rest.len() - 1];
    for mid in &rest[..rest.len() - 1] {
        match remaining.find(mid) {
            Some(pos) => remaining = &remaining[pos + mid.len()..],
            None => return false,
        }
    }
    remaining.ends_with(last)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn matcher_semantics() {
        assert!(key_expr_matches("a/pprz/**", "a/pprz/5/X"));
        assert!(key_expr_matches("a/**", "a"));
        assert!(key_expr_matches("a/pprz/*/X", "a/pprz/5/X"));
        assert!(!key_expr_matches("a/pprz/*/X", "a/pprz/5/Y"));
        assert!(key_expr_matches("a/pprz/5/X$*", "a/pprz/5/X"));
        assert!(key_expr_matches("a/pprz/5/X$*", "a/pprz/5/X_MIN"));
        assert!(!key_expr_matches("a/pprz/5/X$*", "a/pprz/5/Y"));
        assert!(key_expr_matches("a/pprz/1$*/A$*B", "a/pprz/12/AxxB"));
        assert!(!key_expr_matches("a/pprz/1$*/A$*B", "a/pprz/12/AxxBy"));
        assert!(!key_expr_matches("a/*", "a/b/c"));
    }
}

//! Scenes of many copters, parsed a chunk of copters at a time.
//!
//! The TOML parser builds a tree of the whole text, spans and keys included, before serde
//! reads it: about 35 times the text's size. A generated swarm of 100,000 copters is 25 MB
//! of TOML, and its tree peaked at 890 MB, twice what the run then holds. When the
//! `[[copter]]` tables come last, the head (everything before the first) is parsed alone and
//! the copters [`COPTERS_PER_CHUNK`] at a time; each chunk is a TOML document of its own. The
//! result is that of one parse of the whole text, and so is an error's location and field
//! path (tested below). Of several errors, the first reported may differ: the head is read
//! whole before any copter, where one parse reports any syntax error before any field error.

use std::ops::Range;

use serde::Deserialize;

use super::{CopterSpec, FieldPath, PathSeg, SceneError, SceneSpec, line_col, parse_whole, path_at};

/// Texts from this size on are parsed in chunks where they can be.
pub(super) const CHUNKED_FROM_BYTES: usize = 1 << 20;

/// Copters per chunk: a chunk's tree is a few megabytes.
pub(super) const COPTERS_PER_CHUNK: usize = 1024;

/// The byte offsets of the `[[copter]]` header lines, if the text can be parsed in chunks:
/// nothing but copter tables from the first on (every other header is `[copter.…]` or
/// `[[copter.…]]`), no copter table nor `copter` key before it, and no multi-line string
/// anywhere (a line of one could look like a header). `None`: parse the whole text.
pub(super) fn copter_headers(text: &str) -> Option<Vec<usize>> {
    if text.contains("\"\"\"") || text.contains("'''") {
        return None;
    }
    let (mut starts, mut offset) = (Vec::new(), 0);
    for line in text.split_inclusive('\n') {
        let t = line.trim();
        if t == "[[copter]]" {
            starts.push(offset);
        } else if starts.is_empty() && names_copters(t) {
            // `copter = [...]` or `copter.x = ...` in the head: one parse says what it means.
            return None;
        } else if t.starts_with('[') {
            let copter_table = t.starts_with("[copter.") || t.starts_with("[[copter.");
            if starts.is_empty() == copter_table {
                // A copter table before the first header, or another table after it.
                return None;
            }
        }
        offset += line.len();
    }
    (!starts.is_empty()).then_some(starts)
}

/// Whether a line sets a key `copter` (bare or quoted), at the top or in any table.
fn names_copters(line: &str) -> bool {
    ["copter", "\"copter\"", "'copter'"]
        .iter()
        .any(|k| line.strip_prefix(k).is_some_and(|rest| rest.trim_start().starts_with(['=', '.'])))
}

/// Parses `text` whose `[[copter]]` headers start at `starts` (from [`copter_headers`]),
/// `per_chunk` copters at a time.
pub(super) fn from_toml_chunked(
    origin: &str,
    text: &str,
    starts: &[usize],
    per_chunk: usize,
) -> Result<SceneSpec, SceneError> {
    let mut spec = parse_whole(origin, &text[..starts[0]])?;
    if !spec.copters.is_empty() {
        // `copter = [...]` in the head as well: one parse says what is wrong.
        return parse_whole(origin, text);
    }
    #[derive(Deserialize)]
    #[serde(deny_unknown_fields)]
    struct Chunk {
        #[serde(rename = "copter")]
        copters: Vec<CopterSpec>,
    }
    spec.copters.reserve_exact(starts.len());
    for (k, group) in starts.chunks(per_chunk).enumerate() {
        let end = starts.get((k + 1) * per_chunk).copied().unwrap_or(text.len());
        let (begin, first) = (group[0], k * per_chunk);
        let chunk = &text[begin..end];
        let parsed: Chunk = toml::from_str(chunk).map_err(|e| syntax_error(origin, text, begin, chunk, first, &e))?;
        spec.copters.extend(parsed.copters);
    }
    Ok(spec)
}

/// The parse error of `chunk`, the part of `text` from byte `begin` on whose first copter is
/// the scene's `first`, as an error of the whole text: its location in the text, its copter's
/// index in the scene (the whole text is the chunk from 0 with copter 0).
pub(super) fn syntax_error(
    origin: &str,
    text: &str,
    begin: usize,
    chunk: &str,
    first: usize,
    e: &toml::de::Error,
) -> SceneError {
    let (path, location) = match e.span() {
        Some(Range { start, end }) => {
            let mut path = path_at(chunk, &(start..end));
            if let [PathSeg::Key(key), PathSeg::Index(i), ..] = path.0.as_mut_slice()
                && key == "copter"
            {
                *i += first;
            }
            (path, Some(line_col(text, begin + start)))
        }
        None => (FieldPath::default(), None),
    };
    SceneError::Syntax { origin: origin.into(), location, path, message: e.message().trim().to_owned() }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn chunked(text: &str, per_chunk: usize) -> Result<SceneSpec, SceneError> {
        let starts = copter_headers(text).expect("a generated scene parses in chunks");
        from_toml_chunked("s.toml", text, &starts, per_chunk)
    }

    /// 2,500 copters of `scene dense` with its pillars, in TOML.
    fn dense_text() -> String {
        super::super::dense_swarm(2500, 1.5, true, 10, 5).to_toml()
    }

    #[test]
    fn chunks_give_the_scene_of_one_parse() {
        let text = dense_text();
        let one = parse_whole("s.toml", &text).unwrap();
        assert_eq!(one.copters.len(), 2500);
        for per_chunk in [1, 7, 1024, 5000] {
            assert_eq!(chunked(&text, per_chunk).unwrap(), one, "{per_chunk} copters a chunk");
        }
    }

    #[test]
    fn a_chunks_error_is_the_error_of_one_parse() {
        let text = dense_text();
        // Copter 2,345's start position a string, and an unknown field in copter 1,100's command.
        let at = text.match_indices("[copter.start]\npos_m = ").nth(2345).unwrap().0 + 23;
        let value_end = at + text[at..].find(']').unwrap() + 1;
        let bad_pos = format!("{}\"here\"{}", &text[..at], &text[value_end..]);
        let at = text.match_indices("[copter.command]\n").nth(1100).unwrap().0 + 17;
        let unknown = format!("{}speed = 3\n{}", &text[..at], &text[at..]);
        for (bad, field) in [(bad_pos, "copter[2345].start.pos_m"), (unknown, "copter[1100].command.speed")] {
            let one = parse_whole("s.toml", &bad).unwrap_err();
            assert_eq!(one.path().to_string(), field, "{one}");
            for per_chunk in [7, 1024] {
                let got = chunked(&bad, per_chunk).unwrap_err();
                assert_eq!(got.to_string(), one.to_string(), "{per_chunk} copters a chunk");
            }
        }
    }

    #[test]
    fn texts_that_cannot_be_cut_at_the_copters_are_parsed_whole() {
        let text = dense_text();
        // A table after the copters, a copter table before the first, a multi-line string.
        let after = format!("{text}\n[arena]\nheight_m = 3.0\n");
        let before = text.replacen("[[copter]]", "[copter.start]\npos_m = [0.0, 0.0]\n\n[[copter]]", 1);
        let string = text.replacen("name = \"c7\"", "name = \"\"\"c7\"\"\"", 1);
        // An empty array of copters first: one parse refuses the copter tables after it.
        let key = format!("copter = []\n{text}");
        assert!(parse_whole("s.toml", &key).is_err());
        for t in [after, before, string, key] {
            assert!(copter_headers(&t).is_none());
        }
        // And a header line that is not exactly `[[copter]]` (a comment after it).
        let commented = text.replacen("[[copter]]\nname = \"c9\"", "[[copter]] # nine\nname = \"c9\"", 1);
        assert!(copter_headers(&commented).is_none());
    }
}

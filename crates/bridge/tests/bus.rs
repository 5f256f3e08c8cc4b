//! The Ivy-style bus: captures, bind_from, unbind at runtime, limits, and
//! key-expression narrowing (examples plus an exhaustive property check).

mod common;

use std::sync::{Arc, Mutex};

use bridge::paparazzi::bus::narrow;
use bridge::paparazzi::codec::{Sender, encode};
use bridge::paparazzi::narrow::ChunkPattern;
use bridge::zenoh_net::keyexpr::{key_expr_matches, key_for_text, narrow_key_expr};
use bridge::{BindId, Bus, BusError, MessageSet};
use regex::Regex;

use common::{Gen, asset};

type Log = Arc<Mutex<Vec<(BindId, Vec<String>)>>>;

fn logger(log: &Log) -> impl FnMut(&bridge::Delivery<'_>, &mut bridge::Control) + Send + 'static {
    let log = Arc::clone(log);
    move |d, _| {
        let caps = d.captures.iter().map(|s| s.to_string()).collect();
        log.lock().expect("lock").push((d.bind_id, caps));
    }
}

fn taken(log: &Log) -> Vec<(BindId, Vec<String>)> {
    std::mem::take(&mut *log.lock().expect("lock"))
}

#[test]
fn delivers_capture_groups_like_ivy() {
    let mut bus = Bus::new();
    let log: Log = Arc::default();
    let id = bus.bind(r"^(\S*) ATTITUDE (\S+) (\S+) (\S+)( extra)?", logger(&log)).expect("bind");
    assert_eq!(bus.dispatch("k", "5 ATTITUDE 0.1 -0.2 0.3"), 1);
    assert_eq!(bus.dispatch("k", "5 ROTORCRAFT_FP 1 2 3"), 0);
    let got = taken(&log);
    assert_eq!(got, [(id, vec!["5".into(), "0.1".into(), "-0.2".into(), "0.3".into(), String::new()])]);
    // A pattern without groups gets no captures; unanchored patterns search.
    let id2 = bus.bind("SONAR", logger(&log)).expect("bind");
    bus.dispatch("k", "7 SONAR_ARRAY 1 2 3 4");
    assert_eq!(taken(&log), [(id2, vec![])]);
}

#[test]
fn bind_from_receives_from_one_aircraft_only() {
    let mut bus = Bus::new();
    let log: Log = Arc::default();
    let id = bus.bind_from(5, r"^(\S*) ATTITUDE (.*)", logger(&log)).expect("bind");
    for text in [
        "5 ATTITUDE 1 2 3",
        "6 ATTITUDE 1 2 3",
        "55 ATTITUDE 1 2 3",
        "15 ATTITUDE 1 2 3",
        "ground ATTITUDE 1",
        "5 ATTITUDE 4 5 6",
    ] {
        bus.dispatch("k", text);
    }
    let got: Vec<String> = taken(&log)
        .into_iter()
        .map(|(i, c)| {
            assert_eq!(i, id);
            c[1].clone()
        })
        .collect();
    assert_eq!(got, ["1 2 3", "4 5 6"]);
    assert_eq!(bridge::zenoh_net::keyexpr::bus_key_exprs(&bus, "twinswarm/lab"), ["twinswarm/lab/pprz/5/ATTITUDE"]);
}

#[test]
fn unbind_at_runtime_outside_and_inside_handlers() {
    let mut bus = Bus::new();
    let log: Log = Arc::default();
    let a = bus.bind(r"^\S+ PING", logger(&log)).expect("bind");
    let b = bus.bind(r"^\S+ PING", logger(&log)).expect("bind");
    assert_eq!(bus.dispatch("k", "1 PING"), 2);
    assert!(bus.unbind(a));
    assert!(!bus.unbind(a), "second unbind is a no-op");
    assert_eq!(bus.dispatch("k", "1 PING"), 1);
    assert!(bus.unbind(b));
    assert!(bus.is_empty());
    taken(&log);

    // One-shot binding: unbinds itself on its first delivery.
    let count = Arc::new(Mutex::new(0));
    let c2 = Arc::clone(&count);
    bus.bind(r"^\S+ PONG", move |_, ctl| {
        *c2.lock().expect("lock") += 1;
        ctl.unbind_self();
    })
    .expect("bind");
    bus.dispatch("k", "1 PONG");
    bus.dispatch("k", "1 PONG");
    assert_eq!(*count.lock().expect("lock"), 1);
    assert!(bus.is_empty());

    // A handler unbinds a later binding: it does not run in this dispatch.
    let victim = Arc::new(Mutex::new(None::<BindId>));
    let v2 = Arc::clone(&victim);
    let first = bus
        .bind(r"^(\S+) ALIVE", move |_, ctl| {
            if let Some(id) = *v2.lock().expect("lock") {
                ctl.unbind(id);
            }
        })
        .expect("bind");
    let second = bus.bind(r"ALIVE", logger(&log)).expect("bind"); // unnamed index
    *victim.lock().expect("lock") = Some(second);
    assert_eq!(bus.dispatch("k", "3 ALIVE 1"), 1);
    assert!(taken(&log).is_empty());
    assert_eq!(bus.len(), 1);
    assert_eq!(bus.bindings()[0].id, first);
}

#[test]
fn handlers_run_in_bind_order_across_indexes() {
    let mut bus = Bus::new();
    let log: Log = Arc::default();
    let ids = [
        bus.bind(r"ATTITUDE", logger(&log)).expect("bind"),     // unnamed
        bus.bind(r"^5 ATTITUDE ", logger(&log)).expect("bind"), // named
        bus.bind(r"^(.*)$", logger(&log)).expect("bind"),       // unnamed
        bus.bind(r"^\S+ ATTITUDE( |$)", logger(&log)).expect("bind"), // named
    ];
    assert_eq!(bus.dispatch("k", "5 ATTITUDE 1 2 3"), 4);
    let order: Vec<BindId> = taken(&log).into_iter().map(|(i, _)| i).collect();
    assert_eq!(order, ids);
}

#[test]
fn bad_and_oversize_patterns_are_errors() {
    let mut bus = Bus::new();
    assert!(matches!(bus.bind("(", |_, _| {}), Err(BusError::BadPattern { .. })));
    assert!(matches!(bus.bind(r"(\w{100}){100}", |_, _| {}), Err(BusError::PatternTooLarge { .. })));
    let long = "a".repeat(5000);
    assert!(matches!(bus.bind(&long, |_, _| {}), Err(BusError::PatternTooLong { len_bytes: 5000, .. })));
    assert!(bus.is_empty());
    // Catastrophic-backtracking patterns are harmless: matching is linear.
    bus.bind(r"^(a+)+$", |_, _| {}).expect("bind");
    let text = format!("1 X {}b", "a".repeat(100_000));
    assert_eq!(bus.dispatch("k", &text), 0);
}

const PREFIX: &str = "twinswarm/lab";

#[test]
fn narrowing_examples() {
    let cases = [
        (r"^(\S*) ATTITUDE (.*)", "twinswarm/lab/pprz/*/ATTITUDE"),
        // Matches ROTORCRAFT_FP_MIN too, so the name cannot be exact.
        (r"^5 ROTORCRAFT_FP", "twinswarm/lab/pprz/5/ROTORCRAFT_FP$*"),
        (r"^5 ROTORCRAFT_FP( .*|$)", "twinswarm/lab/pprz/5/ROTORCRAFT_FP"),
        (r"^5 ROTORCRAFT_FP ", "twinswarm/lab/pprz/5/ROTORCRAFT_FP"),
        (r"\A5 ROTORCRAFT_FP\z", "twinswarm/lab/pprz/5/ROTORCRAFT_FP"),
        (r"^([^ ]*) +(ATTITUDE( .*|$))", "twinswarm/lab/pprz/*/ATTITUDE"), // pprzlink OCaml message_bind
        (r"^([^ ]* +ATTITUDE( .*|$))", "twinswarm/lab/pprz/*/ATTITUDE"),   // pprzlink Python subscribe
        (r"^ground_dl VIRTUAL_SONAR (.*)", "twinswarm/lab/pprz/ground_dl/VIRTUAL_SONAR"),
        (r"^\d+ SONAR_ARRAY (\d+) (\d+)", "twinswarm/lab/pprz/*/SONAR_ARRAY"),
        (r"^(\S*) FINKEN_(\S*) ", "twinswarm/lab/pprz/*/FINKEN_$*"),
        (r"^1\d ATTITUDE$", "twinswarm/lab/pprz/1$*/ATTITUDE"),
        (r"^5 (.*)", "twinswarm/lab/pprz/5/*"),
        (r"^5 *ATTITUDE", "twinswarm/lab/pprz/5$*/*"),
        (r"(?i)^5 attitude ", "twinswarm/lab/pprz/5/*"),
        (r"ATTITUDE", "twinswarm/lab/pprz/**"),
        (r"(.*)", "twinswarm/lab/pprz/**"),
        (r"(?m)^5 ATTITUDE ", "twinswarm/lab/pprz/**"),
        (r"^.* ATTITUDE", "twinswarm/lab/pprz/**"),
        (r"^5$", "twinswarm/lab/pprz/**"),
        (r"^\s*5 ATTITUDE", "twinswarm/lab/pprz/**"),
    ];
    for (pattern, expected) in cases {
        assert_eq!(narrow_key_expr(PREFIX, pattern).as_deref(), Ok(expected), "{pattern}");
    }
    assert_eq!(narrow(r"^5 ATTITUDE ").map(|n| n.sender), Ok(ChunkPattern::Exact("5".into())));
    assert!(matches!(narrow_key_expr(PREFIX, "("), Err(BusError::BadPattern { .. })));
}

/// Texts: every message of our messages.xml with several senders, plus
/// edge cases around the header.
fn corpus() -> Vec<String> {
    let set = MessageSet::from_file(asset("paparazzi/messages.xml")).unwrap_or_else(|e| panic!("{e}"));
    let senders = [
        Sender::Aircraft(5),
        Sender::Aircraft(6),
        Sender::Aircraft(15),
        Sender::Aircraft(55),
        Sender::Aircraft(101),
        Sender::ground(),
        Sender::Agent("ground_dl".into()),
    ];
    let mut texts = Vec::new();
    for (i, def) in set.iter().enumerate() {
        for (j, s) in senders.iter().enumerate() {
            let values = Gen::new((i * 31 + j) as u64).values(def);
            texts.push(encode(s, def, &values).expect("encodes"));
        }
    }
    for t in [
        "5 ROTORCRAFT_FP_MIN 1 2 3",
        "5 ROTORCRAFT_FP",
        "5  ATTITUDE 1 2 3",
        "5   ATTITUDE",
        "5 ATTITUDEX 1 2 3",
        "5 ATTITUDE",
        "5 ATTITUDE ",
        "15 ATTITUDE 5 ATTITUDE",
        "ground ATTITUDE 5 ATTITUDE 1",
        "5 FINKEN_X 1",
        "5 FINKEN_",
        "1 X aaaa",
        "5 attitude 1 2 3",
        "5 Attitude 1",
        "12 ATTITUDE 1 2 3",
        "5 5 5",
        "a/b X 1",
        "55 SONAR_ARRAY 1 2 3 4",
        "6 SONAR_ARRAY 10 20 30 40",
        "ground_dl VIRTUAL_SONAR 5 1 2 3 4",
    ] {
        texts.push(t.to_owned());
    }
    texts
}

/// Patterns: the product of anchors, sender parts, separators, names and
/// tails, covering the shapes Paparazzi tools use and many they do not.
fn patterns() -> Vec<String> {
    let anchors = ["^", r"\A", "", "(?m)^"];
    let senders = ["5", r"\d+", r"(\S*)", "([^ ]*)", r"1\d", ".*", "(5|6)", "", "ground_dl", r"\w+"];
    let seps = [" ", " +", " *", r"\s", r"\s+", "", "  "];
    let names = ["ATTITUDE", "ROTORCRAFT_FP", r"FINKEN_\S*", r"(\S*)", "[A-Z_]+", ".*", "SONAR_ARRAY", "(?i:attitude)"];
    let tails = ["", " ", "( .*|$)", "$", "(.*)", r"\b", r" (\S+)", r"\z", r"(\s|$)"];
    let mut out = Vec::new();
    for a in anchors {
        for s in senders {
            for sep in seps {
                for n in names {
                    for t in tails {
                        out.push(format!("{a}{s}{sep}{n}{t}"));
                    }
                }
            }
        }
    }
    out
}

#[test]
fn narrowed_key_never_excludes_a_matching_message() {
    let texts: Vec<(String, String)> =
        corpus().into_iter().filter_map(|t| key_for_text(PREFIX, &t).ok().map(|k| (t, k))).collect();
    assert!(texts.len() > 60);
    let mut checked = 0usize;
    let mut narrowed = 0usize;
    for p in patterns() {
        let re = Regex::new(&p).unwrap_or_else(|e| panic!("{p}: {e}"));
        let ke = narrow_key_expr(PREFIX, &p).unwrap_or_else(|e| panic!("{p}: {e}"));
        if ke != format!("{PREFIX}/pprz/**") {
            narrowed += 1;
        }
        for (text, key) in &texts {
            if re.is_match(text) {
                checked += 1;
                assert!(key_expr_matches(&ke, key), "pattern `{p}` matches `{text}` (key {key}) but narrowed to {ke}");
            }
        }
    }
    assert!(checked > 10_000, "only {checked} matching pairs");
    assert!(narrowed > 1_000, "only {narrowed} patterns narrowed");
}

/// The same property checked against Zenoh's own key-expression algebra, not the project's
/// matcher: for every text a regex matches, Zenoh's `KeyExpr` of the narrowed expression
/// includes (and so intersects) the text's key. Zenoh delivers a sample to a subscriber
/// exactly when the subscription intersects the key, so narrowing never loses a text Zenoh
/// would deliver. Also: the project's matcher agrees with Zenoh's on every (expression, key).
#[test]
fn narrowed_key_never_excludes_a_matching_message_by_zenohs_own_rules() {
    use zenoh::key_expr::KeyExpr;
    let texts: Vec<(String, KeyExpr<'static>)> = corpus()
        .into_iter()
        .filter_map(|t| {
            let k = key_for_text(PREFIX, &t).ok()?;
            Some((t, KeyExpr::try_from(k).expect("a text's key is a valid key expression")))
        })
        .collect();
    let mut checked = 0usize;
    let mut globbed = 0usize;
    for p in patterns() {
        let re = Regex::new(&p).unwrap_or_else(|e| panic!("{p}: {e}"));
        let ke_text = narrow_key_expr(PREFIX, &p).unwrap_or_else(|e| panic!("{p}: {e}"));
        let ke = KeyExpr::try_from(ke_text.clone()).unwrap_or_else(|e| panic!("{p} narrowed to {ke_text}: {e}"));
        globbed += usize::from(ke_text.contains("$*"));
        for (text, key) in &texts {
            let zenoh_delivers = ke.intersects(key);
            assert_eq!(ke.includes(key), zenoh_delivers, "{ke} vs {key}: a key has no wildcards");
            assert_eq!(
                key_expr_matches(&ke_text, key.as_str()),
                zenoh_delivers,
                "the project's matcher disagrees with Zenoh on {ke} vs {key}"
            );
            if re.is_match(text) {
                checked += 1;
                assert!(zenoh_delivers, "pattern `{p}` matches `{text}` but Zenoh would not deliver {key} to {ke}");
            }
        }
    }
    assert!(checked > 10_000, "only {checked} matching pairs");
    assert!(globbed > 10, "only {globbed} narrowed expressions use `$*`");
}

#[test]
fn dispatch_agrees_with_brute_force_matching() {
    let texts = corpus();
    let pats: Vec<String> = patterns().into_iter().step_by(7).collect();
    let mut bus = Bus::new();
    let log: Log = Arc::default();
    let mut plain = Vec::new();
    for (i, p) in pats.iter().enumerate() {
        let from = (i % 5 == 0).then_some(5u8);
        let id = match from {
            Some(ac) => bus.bind_from(ac, p, logger(&log)),
            None => bus.bind(p, logger(&log)),
        }
        .expect("bind");
        plain.push((id, Regex::new(p).expect("regex"), from));
    }
    for text in &texts {
        bus.dispatch("k", text);
        let got: Vec<BindId> = taken(&log).into_iter().map(|(i, _)| i).collect();
        let sender = text.split(' ').next().unwrap_or("");
        let expected: Vec<BindId> = plain
            .iter()
            .filter(|(_, re, from)| re.is_match(text) && from.is_none_or(|ac| sender == ac.to_string()))
            .map(|(id, _, _)| *id)
            .collect();
        assert_eq!(got, expected, "text `{text}`");
    }
}

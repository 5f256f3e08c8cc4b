//! `recover`: a log cut at any offset gives a complete, valid file with everything up to the
//! last complete chunk; the writer flushes a chunk every simulated second, so little is lost.

use std::path::PathBuf;

use bridge::log::{LogFile, LogMeta, LogOptions, LogReadError, Logger, recover};

fn temp_dir(tag: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("twinswarm-log-{tag}-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

const STEPS: u64 = 200; // 10 s

#[test]
fn recover_rescues_complete_chunks_at_every_cut() {
    let dir = temp_dir("recover");
    let path = dir.join("run.mcap");
    let text = sim_core::scene::DEFAULT_SCENE_TOML;
    let (_, world) = sim_core::scene::load("lab.toml", text).unwrap();
    let n = world.copters.len() as u64;
    let mut state = world.initial_state();
    let inputs = world.initial_inputs();
    let options = LogOptions::default();
    let mut log = Logger::with_options(&path, &world, text, LogMeta::default(), options).unwrap();
    for _ in 0..STEPS {
        let r = sim_core::step(&world, &mut state, &inputs);
        log.log_step(&world, &state, &inputs, &r).unwrap();
    }
    log.finish().unwrap();
    let bytes = std::fs::read(&path).unwrap();
    let full = LogFile::open(&path).unwrap().info().unwrap();
    assert!(full.chunks >= STEPS / 20, "a chunk per simulated second at least: {}", full.chunks);

    // The complete file recovers whole.
    let fixed = dir.join("fixed-full.mcap");
    let r = recover(&path, &fixed).unwrap();
    assert!(r.complete);
    assert_eq!(r.total_messages(), full.messages);
    assert_eq!((r.attachments, r.metadata), (2, 1));

    let mut last_states = 0;
    let cuts = [
        bytes.len() / 10,
        bytes.len() / 4,
        bytes.len() / 2,
        bytes.len() * 3 / 4,
        bytes.len() * 9 / 10,
        bytes.len() - 40,
    ];
    for cut in cuts {
        let broken = dir.join("broken.mcap");
        std::fs::write(&broken, &bytes[..cut]).unwrap();
        let fixed = dir.join(format!("fixed-{cut}.mcap"));
        let r = recover(&broken, &fixed).unwrap_or_else(|e| panic!("cut at {cut}: {e}"));
        // The result is a complete file: footer, summary, CRCs and messages all check.
        let file = LogFile::open(&fixed).unwrap_or_else(|e| panic!("cut at {cut}: {e}"));
        let info = file.info().unwrap();
        assert_eq!(info.messages, r.total_messages());
        assert_eq!(info.attachments.len(), 2, "cut at {cut}: attachments come first");
        assert!(info.metadata.contains_key("twinswarm"));
        let states = file.messages::<bridge::log::proto::CopterState>("/copters/state").unwrap();
        let ticks: Vec<u64> = states.iter().map(|(_, v)| v.tick).collect();
        assert!(ticks.windows(2).all(|w| w[0] <= w[1]));
        assert!(states.len() >= last_states, "cut at {cut}: fewer messages than an earlier cut");
        last_states = states.len();
        // Everything but the last second or so is there: bytes are roughly linear in time.
        let expected_ticks = STEPS as f64 * cut as f64 / bytes.len() as f64;
        let got = ticks.last().copied().unwrap_or(0) as f64;
        assert!(
            got >= expected_ticks - 30.0,
            "cut at {cut} ({expected_ticks:.0} ticks): only {got} ticks recovered: {r:?}"
        );
        // A cut inside the summary section still has the whole data section.
        assert!(r.complete || r.stopped_by.is_some(), "cut at {cut}: {r:?}");
        if cut < bytes.len() * 9 / 10 {
            assert!(!r.complete, "cut at {cut}: {r:?}");
        }
    }
    assert!(last_states as u64 >= (STEPS - 25) * n);

    // Not a log at all: a clear error.
    let junk = dir.join("junk.mcap");
    std::fs::write(&junk, b"").unwrap();
    assert!(matches!(recover(&junk, &dir.join("x.mcap")), Err(LogReadError::Empty { .. })));
    std::fs::write(&junk, b"hello").unwrap();
    assert!(matches!(recover(&junk, &dir.join("x.mcap")), Err(LogReadError::NotMcap { .. })));
    let _ = std::fs::remove_dir_all(&dir);
}

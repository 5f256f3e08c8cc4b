//! The AFL++ harness: `twinswarm-afl TARGET` runs one target of [`twinswarm_fuzz::TARGETS`]
//! in AFL++'s persistent mode, reading each input from stdin. Built by `scripts/fuzz.sh`.

fn main() {
    let name = std::env::args().nth(1).unwrap_or_default();
    let Some(target) = twinswarm_fuzz::target(&name) else {
        let names: Vec<&str> = twinswarm_fuzz::TARGETS.iter().map(|(n, _)| *n).collect();
        eprintln!("usage: twinswarm-afl TARGET (one of: {})", names.join(", "));
        std::process::exit(2);
    };
    afl::fuzz!(|data: &[u8]| target(data));
}

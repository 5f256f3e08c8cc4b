//! The AFL++ harness: `twinswarm-afl TARGET` runs one target of [`twinswarm_fuzz::TARGETS`]
//! in AFL++'s persistent mode, reading each input from stdin. Built by `scripts/fuzz.sh`.
//! `twinswarm-afl --seeds TARGET DIR` writes the target's generated seeds into DIR.

fn main() {
    let name = std::env::args().nth(1).unwrap_or_default();
    if name == "--seeds" {
        let (target, dir) = (std::env::args().nth(2).unwrap_or_default(), std::env::args().nth(3).unwrap_or_default());
        for (k, data) in twinswarm_fuzz::seeds(&target).iter().enumerate() {
            std::fs::write(std::path::Path::new(&dir).join(format!("generated-{k}")), data).expect("a seed written");
        }
        return;
    }
    let Some(target) = twinswarm_fuzz::target(&name) else {
        let names: Vec<&str> = twinswarm_fuzz::TARGETS.iter().map(|(n, _)| *n).collect();
        eprintln!("usage: twinswarm-afl TARGET (one of: {})", names.join(", "));
        std::process::exit(2);
    };
    afl::fuzz!(|data: &[u8]| target(data));
}

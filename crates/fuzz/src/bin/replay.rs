//! Runs one fuzz target on files, without AFL++: `twinswarm-fuzz-replay TARGET FILE...`.
//! For a crash file from `scripts/fuzz.sh` (`target/afl/out/<target>/default/crashes/`):
//! the panic message and backtrace of the uninstrumented code.
//! `twinswarm-fuzz-replay --seeds TARGET DIR` writes the target's generated seeds into DIR.

fn main() {
    let mut args = std::env::args().skip(1);
    let mut name = args.next().unwrap_or_default();
    if name == "--seeds" {
        name = args.next().unwrap_or_default();
        let dir = std::path::PathBuf::from(args.next().unwrap_or_else(|| ".".into()));
        for (k, data) in twinswarm_fuzz::seeds(&name).iter().enumerate() {
            let path = dir.join(format!("generated-{k}"));
            if let Err(e) = std::fs::write(&path, data) {
                eprintln!("cannot write {}: {e}", path.display());
                std::process::exit(2);
            }
        }
        return;
    }
    let Some(target) = twinswarm_fuzz::target(&name) else {
        let names: Vec<&str> = twinswarm_fuzz::TARGETS.iter().map(|(n, _)| *n).collect();
        eprintln!("usage: twinswarm-fuzz-replay TARGET FILE... (TARGET one of: {})", names.join(", "));
        std::process::exit(2);
    };
    for path in args {
        match std::fs::read(&path) {
            Ok(data) => {
                target(&data);
                println!("ok {path}");
            }
            Err(e) => {
                eprintln!("cannot read {path}: {e}");
                std::process::exit(2);
            }
        }
    }
}

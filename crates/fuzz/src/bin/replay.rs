//! Runs one fuzz target on files, without AFL++: `twinswarm-fuzz-replay TARGET FILE...`.
//! For a crash file from `scripts/fuzz.sh` (`target/afl/out/<target>/default/crashes/`):
//! the panic message and backtrace of the uninstrumented code.

fn main() {
    let mut args = std::env::args().skip(1);
    let name = args.next().unwrap_or_default();
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

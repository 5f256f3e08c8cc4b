//! The cost of MCAP logging: one 50 ms control step of N hovering FINkens with sensors on,
//! logging off versus on (every state, sensor reading, command, controller output, transform
//! and 3D view, to a file in a temporary directory), N = 100, 1000 and 10 000, on 1 and 2
//! threads. The step thread only copies numbers; the logger's writer thread encodes and
//! compresses, and the step waits for it only when it falls behind (see docs/logging.md's
//! table, made with `swarm_rt --log-cost`).
//!
//! A second group, `mcap_writer`, writes protobuf messages (20 steps of 1,000 hovering
//! copters, as the logger encodes them) through the `mcap` crate's `Writer` with the logger's
//! settings (zstd level 3, 1 MiB chunks, every CRC), into memory: the writer thread's cost
//! per byte (docs/performance.md, with the project's former chunk writer beside it).
//!
//! `cargo bench -p twinswarm --bench log [-- mcap_writer]`

use std::collections::BTreeMap;

use bridge::log::{Encoder, StepFrame, Topic, schema_data};
use criterion::{BenchmarkId, Criterion, Throughput, criterion_group, criterion_main};
use mcap::records::MessageHeader;
use sim_core::{scene, step};

fn bench_log(c: &mut Criterion) {
    let mut group = c.benchmark_group("log_step_50ms");
    let dir = std::env::temp_dir().join(format!("twinswarm-bench-log-{}", std::process::id()));
    if let Err(e) = std::fs::create_dir_all(&dir) {
        panic!("cannot create {}: {e}", dir.display());
    }
    for threads in [1usize, 2] {
        for n in [100usize, 1000, 10_000] {
            let mut spec = scene::grid_swarm(n, 2.0, 0.8, true);
            spec.sim.threads = threads;
            let world = match scene::compile(&spec) {
                Ok(w) => w,
                Err(e) => panic!("{e}"),
            };
            group.sample_size(if n >= 1000 { 10 } else { 30 });
            let inputs = world.initial_inputs();
            for logging in [false, true] {
                let mut state = world.initial_state();
                for _ in 0..20 {
                    step(&world, &mut state, &inputs);
                }
                let label = format!("{}_{threads}t", if logging { "log_on" } else { "log_off" });
                if logging {
                    let path = dir.join("bench.mcap");
                    let meta = bridge::log::LogMeta::default();
                    let mut log = match bridge::log::Logger::create(&path, &world, "", meta) {
                        Ok(l) => l,
                        Err(e) => panic!("{e}"),
                    };
                    group.bench_with_input(BenchmarkId::new(label, n), &n, |b, _| {
                        b.iter(|| {
                            let r = step(&world, &mut state, &inputs);
                            if let Err(e) = log.log_step(&world, &state, &inputs, &r) {
                                panic!("{e}");
                            }
                        })
                    });
                    if let Err(e) = log.finish() {
                        panic!("{e}");
                    }
                } else {
                    group.bench_with_input(BenchmarkId::new(label, n), &n, |b, _| {
                        b.iter(|| step(&world, &mut state, &inputs))
                    });
                }
                let crashed = state.copters.iter().filter(|c| c.crash.is_some()).count();
                assert_eq!(crashed, 0, "copters crashed during the benchmark: the numbers would be wrong");
            }
        }
    }
    group.finish();
    let _ = std::fs::remove_dir_all(&dir);
}

/// 20 steps of N = 1,000 hovering copters, encoded as the logger does: (topic, log time, bytes).
fn encoded_messages() -> Vec<(Topic, u64, Vec<u8>)> {
    let world = match scene::compile(&scene::grid_swarm(1000, 2.0, 0.8, true)) {
        Ok(w) => w,
        Err(e) => panic!("{e}"),
    };
    let mut state = world.initial_state();
    let inputs = world.initial_inputs();
    let mut encoder = Encoder::new(&world, 1_700_000_000_000_000_000);
    let mut frame = StepFrame::default();
    let mut out = Vec::new();
    for _ in 0..40 {
        let report = step(&world, &mut state, &inputs);
        if state.tick > 20 {
            frame.capture(&world, &state, &inputs, &report);
            let _ = encoder.encode_step(&frame, false, &mut |t, lt, d: &[u8]| -> Result<(), ()> {
                out.push((t, lt, d.to_vec()));
                Ok(())
            });
        }
    }
    out
}

const ZSTD_LEVEL: u32 = 3;
const CHUNK_BYTES: usize = 1 << 20;

fn bench_writers(c: &mut Criterion) {
    let messages = encoded_messages();
    let bytes: usize = messages.iter().map(|m| m.2.len()).sum();
    let mut group = c.benchmark_group("mcap_writer");
    group.sample_size(20);
    group.throughput(Throughput::Bytes(bytes as u64));
    let header = |channel_id, seq, lt| MessageHeader { channel_id, sequence: seq, log_time: lt, publish_time: lt };
    group.bench_function("mcap_crate_writer", |b| {
        b.iter(|| {
            let mut w = mcap::WriteOptions::new()
                .compression(Some(mcap::Compression::Zstd))
                .compression_level(ZSTD_LEVEL)
                .compression_threads(0)
                .chunk_size(Some(CHUNK_BYTES as u64))
                .create(std::io::Cursor::new(Vec::with_capacity(bytes)))
                .expect("in memory");
            let mut ids = BTreeMap::new();
            for t in Topic::ALL {
                let s = w.add_schema(t.schema(), "protobuf", &schema_data(t.schema()).unwrap_or_default());
                let s = s.expect("in memory");
                ids.insert(t, w.add_channel(s, t.name(), "protobuf", &BTreeMap::new()).expect("in memory"));
            }
            for (i, (t, lt, d)) in messages.iter().enumerate() {
                w.write_to_known_channel(&header(ids[t], i as u32, *lt), d).expect("in memory");
            }
            w.finish().expect("in memory");
            w.into_inner().into_inner().len()
        })
    });
    group.finish();
}

criterion_group!(benches, bench_log, bench_writers);
criterion_main!(benches);

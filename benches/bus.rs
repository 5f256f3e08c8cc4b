//! Throughput of the Ivy-style regex bus with 100 bound regexes: a stream of realistic FINken
//! telemetry texts from 10 aircraft dispatched through `Bus::dispatch`.
//!
//! `cargo bench -p bridge --bench bus`

use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};

use bridge::paparazzi::bus::Bus;
use criterion::{Criterion, Throughput, criterion_group, criterion_main};

fn texts() -> Vec<String> {
    let mut out = Vec::new();
    for ac in 1..=10 {
        out.push(format!("{ac} SONAR_ARRAY 120 85 300 42"));
        out.push(format!("{ac} ATTITUDE 0.01 1.57 -0.02"));
        out.push(format!("{ac} FINKEN_ACTUATORS_SET_POINT 2.5 -1.0 90.0 55.0"));
        out.push(format!("{ac} FINKEN_IR_ADC 0.805 512"));
        out.push(format!("{ac} ROTORCRAFT_FP 256 -512 204 0 0 0 10 -20 6400 256 -512 204 6400 2000 42"));
    }
    out
}

fn bench_bus(c: &mut Criterion) {
    let delivered = Arc::new(AtomicU64::new(0));
    let mut bus = Bus::new();
    let names = ["SONAR_ARRAY", "ATTITUDE", "FINKEN_ACTUATORS_SET_POINT", "FINKEN_IR_ADC", "ROTORCRAFT_FP"];
    // 100 bindings: per-aircraft and any-aircraft patterns with capture groups, a few generic.
    for i in 0..100 {
        let d = delivered.clone();
        let handler = move |_: &bridge::paparazzi::bus::Delivery<'_>, _: &mut bridge::paparazzi::bus::Control| {
            d.fetch_add(1, Ordering::Relaxed);
        };
        let name = names[i % names.len()];
        let r = match i % 4 {
            0 => bus.bind(&format!(r"^(\S*) {name} (\S*) (\S*)"), handler),
            1 => bus.bind_from((i % 10 + 1) as u8, &format!(r"^(\S*) {name} (.*)"), handler),
            2 => bus.bind(&format!(r"^{} {name} (\S+) (\S+)", i % 10 + 1), handler),
            _ => bus.bind(r"^(\S*) (FINKEN_\w+) (.*)", handler),
        };
        if let Err(e) = r {
            panic!("bind {i}: {e}");
        }
    }
    let texts = texts();
    let mut group = c.benchmark_group("regex_bus_100_bindings");
    group.throughput(Throughput::Elements(texts.len() as u64));
    group.bench_function("dispatch", |b| {
        b.iter(|| {
            for t in &texts {
                bus.dispatch("twinswarm/lab/pprz", t);
            }
        })
    });
    group.finish();
    assert!(delivered.load(Ordering::Relaxed) > 0);
}

criterion_group!(benches, bench_bus);
criterion_main!(benches);

//! A warm step does not touch the heap: a counting global allocator watches a run of steps
//! of a hovering swarm with sensors on, with one and with two threads. Copters that Rapier
//! steps (near something, or crashed) are measured too, not asserted: Rapier allocates.
//!
//! One test function only, so no other test of this binary allocates while it counts.

// A global allocator is an `unsafe` trait; this one only forwards to the system allocator.
#![allow(unsafe_code)]

use std::alloc::{GlobalAlloc, Layout, System};
use std::sync::atomic::{AtomicU64, Ordering};

use sim_core::{World, scene, step};

struct Counting;

static ALLOCATIONS: AtomicU64 = AtomicU64::new(0);

unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        ALLOCATIONS.fetch_add(1, Ordering::Relaxed);
        // SAFETY: forwarded unchanged to the system allocator.
        unsafe { System.alloc(layout) }
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        // SAFETY: `ptr` came from `System.alloc` with this layout.
        unsafe { System.dealloc(ptr, layout) }
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        ALLOCATIONS.fetch_add(1, Ordering::Relaxed);
        // SAFETY: forwarded unchanged to the system allocator.
        unsafe { System.realloc(ptr, layout, new_size) }
    }
}

#[global_allocator]
static GLOBAL: Counting = Counting;

fn lab(threads: usize) -> World {
    let (mut spec, _) = scene::load_default();
    spec.sim.threads = threads;
    spec.sensors.crosstalk.enabled = true;
    scene::compile(&spec).unwrap()
}

/// 300 copters in Wall-Avoid, each heading its own way at 0.3 m/s.
fn swarm(threads: usize) -> World {
    let spec = scene::cruising_swarm(300, threads);
    scene::compile(&spec).unwrap()
}

/// Allocations during `steps` steps after `warm` warm-up steps; events (which a report
/// carries in a `Vec`) are counted too, so the caller can tell them apart.
fn allocations(world: &World, warm: usize, steps: usize) -> (u64, usize) {
    let mut state = world.initial_state();
    let inputs = world.initial_inputs();
    for _ in 0..warm {
        step(world, &mut state, &inputs);
    }
    let mut events = 0;
    let before = ALLOCATIONS.load(Ordering::Relaxed);
    for _ in 0..steps {
        events += step(world, &mut state, &inputs).events.len();
    }
    (ALLOCATIONS.load(Ordering::Relaxed) - before, events)
}

fn hover(n: usize, threads: usize) -> World {
    let mut spec = scene::grid_swarm(n, 2.0, 0.8, true);
    spec.sim.threads = threads;
    scene::compile(&spec).unwrap()
}

#[test]
fn a_warm_step_in_free_flight_does_not_allocate() {
    // 200 hovering copters with sensors on, all flying free of Rapier: nothing at all.
    let (n, events) = allocations(&hover(200, 1), 20, 200);
    assert_eq!((n, events), (0, 0), "hover, 1 thread: allocations and events in 200 warm steps");

    // Two threads: sim-core allocates nothing either; rayon's job queue takes a new block of
    // 63 slots every 63 steps (one `install` per step), and nothing else.
    let (n, _) = allocations(&hover(200, 2), 20, 200);
    assert!(n <= 200 / 63 + 1, "hover, 2 threads: {n} allocations in 200 warm steps");

    // Copters handed to Rapier (near walls, boxes and each other, or crashed) do allocate:
    // Rapier 0.36's narrow phase and contact solver build scratch vectors per step. Measured
    // here so a change shows; see docs/performance.md.
    let (lab, _) = allocations(&lab(1), 60, 400);
    let (swarm, events) = allocations(&swarm(1), 20, 100);
    eprintln!(
        "Rapier-side allocations: lab {lab} in 400 steps; Wall-Avoid swarm {swarm} in 100 steps ({events} events)"
    );
}

//! A warm step does not touch the heap outside Rapier: a counting global allocator watches
//! the steps of a hovering swarm (one and two threads), the lab, the lab with a twin and the
//! dense take-off with its crashes, and attributes each allocation by its call stack. Rapier's
//! own (when a copter is near something, or a wreck moves) are measured and printed.
//!
//! One test function only, so no other test of this binary allocates while it counts.

// A global allocator is an `unsafe` trait; this one only forwards to the system allocator.
#![allow(unsafe_code)]

use std::alloc::{GlobalAlloc, Layout, System};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};

use sim_core::{StepReport, World, scene, step_into};

struct Counting;

static ALLOCATIONS: AtomicU64 = AtomicU64::new(0);

thread_local! {
    /// Set while this thread is inside the allocator's own bookkeeping (a backtrace allocates).
    static INSIDE: std::cell::Cell<bool> = const { std::cell::Cell::new(false) };
    /// Set on the thread that steps: with one thread, only its allocations count (a thread
    /// pool of an earlier measurement may still be winding down on others).
    static STEPPER: std::cell::Cell<bool> = const { std::cell::Cell::new(false) };
}

/// Count the allocations of every thread (a two-thread step), not only the stepper's.
static ALL_THREADS: AtomicBool = AtomicBool::new(true);

/// While set, each allocation's call stack is looked at: those made inside Rapier are counted
/// apart, in `RAPIER_ALLOCATIONS`.
static ATTRIBUTE: AtomicBool = AtomicBool::new(false);
static RAPIER_ALLOCATIONS: AtomicU64 = AtomicU64::new(0);

/// Counts one allocation, and whether Rapier made it.
fn count() {
    if INSIDE.with(|f| f.get()) || !(ALL_THREADS.load(Ordering::Relaxed) || STEPPER.with(|f| f.get())) {
        return;
    }
    ALLOCATIONS.fetch_add(1, Ordering::Relaxed);
    if ATTRIBUTE.load(Ordering::Relaxed) && !INSIDE.with(|f| f.replace(true)) {
        let trace = std::backtrace::Backtrace::force_capture().to_string();
        if trace.contains("rapier3d::") {
            RAPIER_ALLOCATIONS.fetch_add(1, Ordering::Relaxed);
        }
        INSIDE.with(|f| f.set(false));
    }
}

unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        count();
        // SAFETY: forwarded unchanged to the system allocator.
        unsafe { System.alloc(layout) }
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        // SAFETY: `ptr` came from `System.alloc` with this layout.
        unsafe { System.dealloc(ptr, layout) }
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        count();
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

/// The lab with a twin of a real copter (aircraft 5) beside the two virtual ones.
fn lab_with_twin() -> World {
    let lab = include_str!("../../../assets/scenes/finken_lab.toml");
    let text = format!(
        "{lab}\n[[copter]]\nname = \"twin5\"\nkind = \"real\"\nac_id = 5\nstart = {{ pos_m = [0.0, 0.9] }}\n\
         command = {{ height_m = 0.8 }}\n"
    );
    scene::load("lab_twin.toml", &text).unwrap().1
}

/// The experiment: 100 copters on a 1.5 m grid taking off among pillars, crashing as they go.
fn dense(threads: usize) -> World {
    let mut spec = scene::dense_swarm(100, 1.5, true, 10, 1);
    spec.sim.threads = threads;
    scene::compile(&spec).unwrap()
}

/// What `steps` steps after `warm` warm-up steps allocated, made by Rapier or by anything
/// else (sim-core), with the steps where Rapier stepped and the events seen.
#[derive(Debug, Default)]
struct Count {
    steps: u64,
    rapier_steps: u64,
    rapier_allocations: u64,
    other_allocations: u64,
    events: usize,
}

fn allocations(world: &World, warm: usize, steps: usize) -> Count {
    let mut state = world.initial_state();
    let inputs = world.initial_inputs();
    let mut report = StepReport::default();
    for _ in 0..warm {
        step_into(world, &mut state, &inputs, &mut report);
    }
    let mut count = Count { steps: steps as u64, ..Count::default() };
    let (all0, rapier0) = (ALLOCATIONS.load(Ordering::Relaxed), RAPIER_ALLOCATIONS.load(Ordering::Relaxed));
    // Rayon's pool (two threads) is not attributed: its job blocks are counted by the caller.
    let one = world.params.threads == 1;
    ATTRIBUTE.store(one, Ordering::Relaxed);
    ALL_THREADS.store(!one, Ordering::Relaxed);
    STEPPER.with(|f| f.set(true));
    for _ in 0..steps {
        step_into(world, &mut state, &inputs, &mut report);
        count.events += report.events.len();
        count.rapier_steps += u64::from(report.rapier_substeps > 0);
    }
    ATTRIBUTE.store(false, Ordering::Relaxed);
    ALL_THREADS.store(true, Ordering::Relaxed);
    let all = ALLOCATIONS.load(Ordering::Relaxed) - all0;
    count.rapier_allocations = RAPIER_ALLOCATIONS.load(Ordering::Relaxed) - rapier0;
    count.other_allocations = all - count.rapier_allocations;
    count
}

fn hover(n: usize, threads: usize) -> World {
    let mut spec = scene::grid_swarm(n, 2.0, 0.8, true);
    spec.sim.threads = threads;
    scene::compile(&spec).unwrap()
}

#[test]
fn a_warm_step_allocates_only_inside_rapier() {
    // 200 hovering copters with sensors on, all flying free of Rapier: nothing at all.
    let c = allocations(&hover(200, 1), 20, 200);
    assert_eq!((c.other_allocations + c.rapier_allocations, c.rapier_steps), (0, 0), "hover, 1 thread: {c:?}");

    // Two threads: sim-core allocates nothing either; rayon's job queue takes a new block of
    // 63 slots every 63 steps (one `install` per step), and nothing else.
    let c = allocations(&hover(200, 2), 20, 200);
    assert!(c.other_allocations <= 200 / 63 + 1, "hover, 2 threads: {c:?}");

    // The lab (walls, table, crate, two Wall-Avoid copters with cross-talk), the lab with a
    // twin, and the experiment with its take-off, crowding and crashes: sim-core allocates
    // nothing in any step. Rapier 0.36 does, in the steps it runs (its narrow phase and
    // solver build scratch vectors), and it drops its list of modified bodies at each step
    // (`RigidBodySet::take_modified`), so the next body that enters or leaves it allocates a
    // new one. Measured and printed, so a change shows; see docs/performance.md.
    for (name, world, warm, steps) in [
        ("lab", lab(1), 60, 600),
        ("lab with a twin", lab_with_twin(), 60, 600),
        ("dense take-off, 100 copters", dense(1), 40, 400),
    ] {
        let c = allocations(&world, warm, steps);
        eprintln!(
            "{name}: {} steps, {} of them with Rapier; Rapier allocated {} times ({:.1} per Rapier step), \
             the rest {} times; {} events",
            c.steps,
            c.rapier_steps,
            c.rapier_allocations,
            c.rapier_allocations as f64 / c.rapier_steps.max(1) as f64,
            c.other_allocations,
            c.events
        );
        assert_eq!(c.other_allocations, 0, "{name}: {c:?}");
        assert!(c.events > 0 || !name.starts_with("dense"), "the experiment crashes: {c:?}");
    }
}

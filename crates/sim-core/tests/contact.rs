//! The closed form makes Rapier's crash decisions: every scenario is flown twice, with
//! `[sim] closed_form = true` (free flight, take-off, landing and floor impacts without
//! Rapier) and `false` (every copter through Rapier at every substep), and the outcomes must
//! agree: whether it crashes, why, when and how fast, and where it ends up.

mod common;

use sim_core::{CrashCause, Event, Inputs, World, step};

#[derive(Debug)]
struct Outcome {
    crash: Option<(CrashCause, u64)>,
    took_off: Option<u64>,
    final_pos: [f32; 3],
    /// Held on the floor in closed form at the end.
    grounded: bool,
}

/// Flies `ticks` control steps; at tick `switch.0` the command's height becomes `switch.1`.
fn fly(world: &World, ticks: u64, switch: Option<(u64, f32)>) -> Outcome {
    let mut state = world.initial_state();
    let mut inputs: Inputs = world.initial_inputs();
    let (mut crash, mut took_off) = (None, None);
    for t in 0..ticks {
        if let Some((at, h)) = switch
            && t == at
        {
            inputs.commands[0].height_m = h;
        }
        for e in step(world, &mut state, &inputs).events {
            match e {
                Event::Crashed { cause, .. } if crash.is_none() => crash = Some((cause, state.tick)),
                Event::TookOff { .. } => took_off = Some(state.tick),
                _ => {}
            }
        }
    }
    let p = state.pose(0).pos_m;
    Outcome { crash, took_off, final_pos: [p.x, p.y, p.z], grounded: state.copters[0].grounded }
}

/// The same copter in closed form and through Rapier.
fn both(copter: &str, arena_m: f32, ticks: u64, switch: Option<(u64, f32)>) -> (Outcome, Outcome) {
    both_with("", copter, arena_m, ticks, switch)
}

/// [`both`] with more scene text after `[sim]` (further tables).
fn both_with(extra: &str, copter: &str, arena_m: f32, ticks: u64, switch: Option<(u64, f32)>) -> (Outcome, Outcome) {
    let fast = common::scene_in_arena(arena_m, &format!("closed_form = true\n{extra}"), copter);
    let rapier = common::scene_in_arena(arena_m, &format!("closed_form = false\n{extra}"), copter);
    assert!(fast.params.closed_form && !rapier.params.closed_form);
    let (a, b) = (fly(&fast, ticks, switch), fly(&rapier, ticks, switch));
    println!("{copter:?}\n  closed form: {a:?}\n  Rapier:      {b:?}");
    (a, b)
}

/// Same crash or none, same cause, within a tick, and for the floor at the same speed (5 %).
fn assert_same_crash(a: &Outcome, b: &Outcome) {
    match (a.crash, b.crash) {
        (None, None) => {}
        (Some((ca, ta)), Some((cb, tb))) => {
            assert!(ta.abs_diff(tb) <= 1, "crash ticks {ta} and {tb}");
            match (ca, cb) {
                (CrashCause::Floor { speed_m_s: va }, CrashCause::Floor { speed_m_s: vb }) => {
                    assert!((va - vb).abs() <= 0.05 * vb, "impact speeds {va} and {vb}");
                }
                (ca, cb) => assert_eq!(std::mem::discriminant(&ca), std::mem::discriminant(&cb), "{ca:?} / {cb:?}"),
            }
        }
        (ca, cb) => panic!("closed form {ca:?}, Rapier {cb:?}"),
    }
}

fn distance(a: [f32; 3], b: [f32; 3]) -> f32 {
    a.iter().zip(&b).map(|(x, y)| (x - y) * (x - y)).sum::<f32>().sqrt()
}

#[test]
fn cutting_the_throttle_crashes_on_the_floor_at_the_same_speed() {
    for z in [0.3, 0.6, 1.0, 2.0] {
        let copter = format!(
            "mode = \"manual\"\nstart = {{ pos_m = [0.0, 0.0], z_m = {z} }}\ncommand = {{ throttle_pct = 0.0 }}"
        );
        let (a, b) = both(&copter, 40.0, 40, None);
        assert!(matches!(a.crash, Some((CrashCause::Floor { .. }, _))), "from {z} m: {a:?}");
        assert_same_crash(&a, &b);
    }
}

#[test]
fn descents_on_a_fixed_throttle_hit_the_floor_at_the_same_speed() {
    // From 1 m, from a free fall to a slow sink of 1.2 m/s (a hover throttle would climb: the
    // battery is full). Landing softly is the next test's.
    for throttle in [5.0, 15.0, 25.0, 30.0, 33.0, 36.0] {
        let copter = format!(
            "mode = \"manual\"\nstart = {{ pos_m = [0.0, 0.0], z_m = 1.0 }}\ncommand = {{ throttle_pct = {throttle} }}"
        );
        let (a, b) = both(&copter, 40.0, 200, None);
        assert!(matches!(a.crash, Some((CrashCause::Floor { .. }, _))), "at {throttle} %: {a:?}");
        assert_same_crash(&a, &b);
    }
}

#[test]
fn take_off_hover_and_landing_agree() {
    // Take off to 0.8 m, hover, land (a height setpoint at the rest height, 0.02 m, descends
    // at 0.3 m/s). Ideal estimation: with the AHRS's biases it would drift sideways at
    // 0.5 m/s and touch down at the crash speed (both ways alike).
    let ideal = "[sensors.estimator]\nideal = true";
    let (a, b) = both_with(ideal, "command = { height_m = 0.8 }", 40.0, 300, Some((150, 0.02)));
    assert_same_crash(&a, &b);
    assert!(a.crash.is_none());
    let (ta, tb) = (a.took_off.expect("took off"), b.took_off.expect("took off"));
    assert!(ta.abs_diff(tb) <= 1, "take-off ticks {ta} and {tb}");
    // It drifts about a metre without position control; the two integrators part a little on
    // the way (0.14 m of 1.2 m with ground effect under the centre, 0.19 m with ground effect
    // under each rotor: the same physics over a flat floor, but not the same rounding).
    let drift = distance(b.final_pos, [0.0, 0.0, b.final_pos[2]]);
    assert!(distance(a.final_pos, b.final_pos) < 0.2 * drift, "landed at {:?} and {:?}", a.final_pos, b.final_pos);
    assert!((a.final_pos[2] - b.final_pos[2]).abs() < 0.005, "landed at {:?} and {:?}", a.final_pos, b.final_pos);
    assert!(a.final_pos[2] < 0.03, "landed: {:?}", a.final_pos);
    assert!(a.grounded, "a landed copter rests on the floor in closed form");
}

#[test]
fn a_copter_flown_into_a_wall_crashes_on_it_both_ways() {
    let copter = "command = { height_m = 1.0, pitch_deg = 8.0 }\nmode = \"mixed_manual\"";
    let (a, b) = both(copter, 4.0, 400, None);
    assert!(matches!(a.crash, Some((CrashCause::Wall, _))), "{a:?}");
    assert_same_crash(&a, &b);
}

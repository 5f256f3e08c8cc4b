//! Crash detection: walls, floor impacts, other copters, tilt.

mod common;

use sim_core::{CrashCause, Event, step};

#[test]
fn a_copter_commanded_into_a_wall_crashes_and_is_reported() {
    let world = common::scene_in_arena(
        4.0,
        "",
        r#"command = { height_m = 1.0, pitch_deg = 8.0 }
mode = "mixed_manual""#,
    );
    let mut state = world.initial_state();
    let inputs = world.initial_inputs();
    let mut crashed = None;
    for _ in 0..400 {
        let r = step(&world, &mut state, &inputs);
        if let Some(Event::Crashed { copter, cause }) = r.events.iter().find(|e| matches!(e, Event::Crashed { .. })) {
            crashed = Some((*copter, *cause, state.tick));
            break;
        }
    }
    let (copter, cause, tick) = crashed.expect("the copter should hit the +x wall");
    assert_eq!(copter, 0);
    assert_eq!(cause, CrashCause::Wall);
    assert!(state.pose(0).pos_m.x > 1.5, "it flew forward (+x) into the wall");
    println!("crashed into the wall at t = {:.2} s", tick as f64 * world.params.control_dt_s);
    // Motors are off from now on, and it falls.
    for _ in 0..60 {
        step(&world, &mut state, &inputs);
    }
    assert_eq!(state.copters[0].rotor_thrust_n, [0.0; 4]);
    assert!(state.pose(0).pos_m.z < 0.2, "a crashed copter falls");
}

#[test]
fn cutting_the_throttle_mid_air_crashes_on_the_floor() {
    let world = common::one_copter_scene(
        "",
        r#"mode = "manual"
start = { pos_m = [0.0, 0.0], z_m = 2.0 }
command = { throttle_pct = 0.0 }"#,
    );
    let mut state = world.initial_state();
    let inputs = world.initial_inputs();
    let mut cause = None;
    for _ in 0..60 {
        for e in step(&world, &mut state, &inputs).events {
            if let Event::Crashed { cause: c, .. } = e {
                cause = Some(c);
            }
        }
    }
    match cause {
        Some(CrashCause::Floor { speed_m_s }) => assert!(speed_m_s > 3.0, "{speed_m_s}"),
        other => panic!("expected a floor crash, got {other:?}"),
    }
}

#[test]
fn a_gentle_takeoff_and_hover_do_not_crash() {
    let world = common::one_copter_scene("", "command = { height_m = 0.8 }");
    let mut state = world.initial_state();
    let inputs = world.initial_inputs();
    let mut took_off = false;
    for _ in 0..100 {
        for e in step(&world, &mut state, &inputs).events {
            assert!(!matches!(e, Event::Crashed { .. }), "{e:?}");
            took_off |= matches!(e, Event::TookOff { copter: 0 });
        }
    }
    assert!(took_off);
}

#[test]
fn two_copters_flying_into_each_other_both_crash() {
    let world = common::load(
        r#"
[arena]
size_m = [10.0, 4.0]
height_m = 3.0
[[copter]]
name = "a"
start = { pos_m = [-1.5, 0.0], z_m = 1.0 }
command = { height_m = 1.0, pitch_deg = 10.0 }
[[copter]]
name = "b"
start = { pos_m = [1.5, 0.0], z_m = 1.0, yaw_deg = 180.0 }
command = { height_m = 1.0, pitch_deg = 10.0 }
"#,
    );
    let mut state = world.initial_state();
    let inputs = world.initial_inputs();
    let mut crashes = Vec::new();
    for _ in 0..200 {
        for e in step(&world, &mut state, &inputs).events {
            if let Event::Crashed { copter, cause } = e {
                crashes.push((copter, cause));
            }
        }
    }
    assert_eq!(crashes.len(), 2, "{crashes:?}");
    assert!(
        crashes.iter().any(|(c, cause)| *c == 0 && matches!(cause, CrashCause::Copter { other: 1, .. })),
        "{crashes:?}"
    );
    assert!(
        crashes.iter().any(|(c, cause)| *c == 1 && matches!(cause, CrashCause::Copter { other: 0, .. })),
        "{crashes:?}"
    );
}

#[test]
fn tilting_past_60_degrees_crashes() {
    // A huge roll command beyond the attitude limit can't tilt it; a manual flip can: give
    // the body a spin directly through a tiny inertia-free kick is not possible from inputs,
    // so lift the command limit instead.
    let world = common::one_copter_scene(
        "",
        r#"start = { pos_m = [0.0, 0.0], z_m = 2.0 }
airframe = { max_tilt_deg = 85.0 }
command = { height_m = 2.0, roll_deg = 80.0 }"#,
    );
    let mut state = world.initial_state();
    let inputs = world.initial_inputs();
    let mut cause = None;
    for _ in 0..40 {
        for e in step(&world, &mut state, &inputs).events {
            if let Event::Crashed { cause: c, .. } = e {
                cause.get_or_insert(c);
            }
        }
    }
    assert!(matches!(cause, Some(CrashCause::Tilt { tilt_deg }) if tilt_deg > 60.0), "{cause:?}");
}

//! Wrecks in closed form (`[sim] closed_form = true`, see `step::fall_wreck`) come to rest
//! where Rapier's wrecks do: every scenario is flown both ways, and the resting places must
//! agree. The closed form's own promises are checked too: a wreck at rest does not move, lies
//! level on the surface it met, and never ends inside a wall or a box.

mod common;

use sim_core::{CrashCause, State, World, step};

/// The scene's copters, each `(x, y, z, throttle %)` in manual mode, and more scene text.
fn scene(closed_form: bool, copters: &[(f32, f32, f32, f32)], extra: &str) -> World {
    let mut text = format!(
        "[sim]\nseed = 7\nclosed_form = {closed_form}\n\n[arena]\nsize_m = [6.0, 6.0]\nheight_m = 4.0\n{extra}\n"
    );
    for (i, (x, y, z, throttle)) in copters.iter().enumerate() {
        text += &format!(
            "\n[[copter]]\nname = \"c{i}\"\nmode = \"manual\"\nstart = {{ pos_m = [{x}, {y}], z_m = {z} }}\ncommand = {{ throttle_pct = {throttle} }}\n"
        );
    }
    common::load(&text)
}

/// Flies `ticks` control steps.
fn fly(world: &World, ticks: u64) -> State {
    let mut state = world.initial_state();
    let inputs = world.initial_inputs();
    for _ in 0..ticks {
        step(world, &mut state, &inputs);
    }
    state
}

/// Both ways: (closed form, Rapier).
fn both(copters: &[(f32, f32, f32, f32)], extra: &str, ticks: u64) -> (State, State) {
    let a = fly(&scene(true, copters, extra), ticks);
    let b = fly(&scene(false, copters, extra), ticks);
    for i in 0..copters.len() {
        let (pa, pb) = (a.pose(i), b.pose(i));
        println!(
            "c{i}: closed form {:?} at {:?} v {:?}; Rapier {:?} at {:?} v {:?}",
            a.copters[i].crash, pa.pos_m, pa.vel_m_s, b.copters[i].crash, pb.pos_m, pb.vel_m_s
        );
    }
    (a, b)
}

/// Copter `i` is a wreck at rest in both runs, level, at about the same place; returns its
/// height in the closed form.
fn assert_rests_alike(a: &State, b: &State, i: usize, within_m: f32) -> f32 {
    let (pa, pb) = (a.pose(i), b.pose(i));
    assert!(a.copters[i].crash.is_some() && b.copters[i].crash.is_some(), "c{i} crashed both ways");
    assert!(a.copters[i].grounded, "c{i}: the closed-form wreck has come to rest");
    assert_eq!(pa.vel_m_s.length(), 0.0, "c{i}: at rest");
    assert!(pb.vel_m_s.length() < 0.05, "c{i}: Rapier's wreck has settled too: {:?}", pb.vel_m_s);
    let [roll, pitch, _] = pa.rpy_rad;
    assert!(roll.abs() < 1e-4 || (roll.abs() - std::f32::consts::PI).abs() < 1e-4, "level: roll {roll}");
    assert!(pitch.abs() < 1e-4, "level: pitch {pitch}");
    let apart = (pa.pos_m - pb.pos_m).length();
    assert!(apart < within_m, "c{i} rests {apart:.3} m from Rapier's wreck");
    // Lying flat on the same surface (Rapier's contacts let it sink a fraction of a mm).
    assert!((pa.pos_m.z - pb.pos_m.z).abs() < 2e-3, "c{i} at {} m, Rapier's at {} m", pa.pos_m.z, pb.pos_m.z);
    pa.pos_m.z
}

#[test]
fn a_wreck_dropped_on_the_floor_lies_where_rapiers_does() {
    for z in [0.6, 1.0, 2.0] {
        let (a, b) = both(&[(0.0, 0.0, z, 0.0)], "", 100);
        assert!(matches!(a.copters[0].crash, Some(CrashCause::Floor { .. })));
        let z = assert_rests_alike(&a, &b, 0, 0.1);
        assert!(z < 0.03, "on the floor: {z} m");
    }
}

#[test]
fn a_wreck_that_hit_a_wall_slides_down_it_to_the_floor() {
    let world =
        common::scene_in_arena(4.0, "", "command = { height_m = 1.0, pitch_deg = 8.0 }\nmode = \"mixed_manual\"");
    let rapier = common::scene_in_arena(
        4.0,
        "closed_form = false",
        "command = { height_m = 1.0, pitch_deg = 8.0 }\nmode = \"mixed_manual\"",
    );
    let (a, b) = (fly(&world, 400), fly(&rapier, 400));
    println!("closed form {:?} {:?}; Rapier {:?} {:?}", a.copters[0].crash, a.pose(0), b.copters[0].crash, b.pose(0));
    assert!(matches!(a.copters[0].crash, Some(CrashCause::Wall)));
    let z = assert_rests_alike(&a, &b, 0, 0.3);
    assert!(z < 0.03, "on the floor, not on the wall: {z} m");
    // Inside the arena: its rotor discs (arm 0.1 m + 63.5 mm) reach no further than the wall.
    let p = a.pose(0).pos_m;
    assert!(p.x.abs().max(p.y.abs()) + 0.1 < 2.0, "inside the walls: {p:?}");
}

#[test]
fn a_wreck_falling_onto_a_box_rests_on_its_top() {
    let table = "[[box]]\nname = \"table\"\npos_m = [0.0, 0.0]\nsize_m = [1.0, 1.0, 0.5]\nyaw_deg = 30.0\n";
    let (a, b) = both(&[(0.1, 0.0, 1.2, 0.0)], table, 100);
    assert!(matches!(a.copters[0].crash, Some(CrashCause::Box { index: 0 })), "{:?}", a.copters[0].crash);
    let z = assert_rests_alike(&a, &b, 0, 0.1);
    assert!(z > 0.5 && z < 0.53, "on the table top (0.5 m): {z} m");
}

#[test]
fn a_wreck_falling_onto_a_wreck_rests_on_top_of_it() {
    // c0 drops from 0.3 m and lies on the floor; c1, 1.2 m above it, lands on it.
    let (a, b) = both(&[(0.0, 0.0, 0.3, 0.0), (0.0, 0.0, 1.5, 0.0)], "", 100);
    assert!(matches!(a.copters[1].crash, Some(CrashCause::Copter { other: 0, .. })), "{:?}", a.copters[1].crash);
    let low = assert_rests_alike(&a, &b, 0, 0.1);
    let high = assert_rests_alike(&a, &b, 1, 0.1);
    assert!(high - low > 0.03, "c1 at {high} m on c0 at {low} m");
}

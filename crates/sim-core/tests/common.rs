//! Helpers shared by the integration tests.
#![allow(dead_code)]

use sim_core::World;

/// A scene with one copter named `c0` in a 40 m square arena. `copter` is the body of its
/// `[[copter]]` table; a start at the origin is added unless it names one.
pub fn one_copter_scene(extra_sim: &str, copter: &str) -> World {
    scene_in_arena(40.0, extra_sim, copter)
}

/// Like [`one_copter_scene`] in a square arena of the given side.
pub fn scene_in_arena(arena_m: f32, extra_sim: &str, copter: &str) -> World {
    let start = if copter.contains("start") { "" } else { "start = { pos_m = [0.0, 0.0] }" };
    let text = format!(
        r#"
[sim]
seed = 7
{extra_sim}

[arena]
size_m = [{arena_m}, {arena_m}]
height_m = 4.0

[[copter]]
name = "c0"
{start}
{copter}
"#
    );
    load(&text)
}

/// Loads a scene, panicking with the error's text.
pub fn load(text: &str) -> World {
    match sim_core::scene::load("test.toml", text) {
        Ok((_, w)) => w,
        Err(e) => panic!("{e}"),
    }
}

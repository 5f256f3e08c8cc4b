//! Scene files: every asset loads, and malformed scenes give exact errors naming the file,
//! line, column and field.

use sim_core::scene::{self, SceneError};

const GOOD: &str = r#"name = "t"

[arena]
size_m = [4.0, 3.0]
height_m = 2.5

[[copter]]
name = "a"
start = { pos_m = [-1.0, 0.0] }
command = { height_m = 0.8 }

[[copter]]
name = "b"
start = { pos_m = [1.0, 0.0] }
"#;

fn error_of(text: &str) -> SceneError {
    match scene::load("bad.toml", text) {
        Ok(_) => panic!("scene unexpectedly accepted:\n{text}"),
        Err(e) => e,
    }
}

fn assert_error(text: &str, want: &str) {
    let e = error_of(text);
    assert_eq!(e.to_string(), want, "full error");
}

#[test]
fn the_base_scene_of_these_tests_is_valid() {
    let (_, world) = scene::load("good.toml", GOOD).unwrap();
    assert_eq!(world.copters.len(), 2);
}

#[test]
fn wrong_type() {
    let text = GOOD.replace("height_m = 2.5", "height_m = \"high\"");
    assert_error(&text, "bad.toml:5:12: arena.height_m: invalid type: string \"high\", expected f32");
}

#[test]
fn missing_field() {
    let text = GOOD.replace("height_m = 2.5\n", "");
    assert_error(&text, "bad.toml:3:1: arena: missing field `height_m`");
}

#[test]
fn unknown_field() {
    let text = GOOD.replace("height_m = 2.5", "height_m = 2.5\ncolour = \"red\"");
    let e = error_of(&text);
    assert_eq!(e.location().map(|l| l.line), Some(6), "{e}");
    assert_eq!(e.path().to_string(), "arena.colour", "{e}");
    assert!(e.message().starts_with("unknown field `colour`, expected one of"), "{e}");
}

#[test]
fn copter_outside_the_arena() {
    let text = GOOD.replace("pos_m = [1.0, 0.0]", "pos_m = [1.95, 0.0]");
    assert_error(
        &text,
        "bad.toml:14:19: copter[1].start.pos_m: copter \"b\" starts outside the arena: its 0.164 m footprint at (1.95, 0, 0.02) must fit in x ∈ [-2, 2], y ∈ [-1.5, 1.5], z ≤ 2.5",
    );
}

#[test]
fn duplicate_names() {
    let text = GOOD.replace("name = \"b\"", "name = \"a\"");
    assert_error(&text, "bad.toml:13:8: copter[1].name: copter name \"a\" is already used by copter[0]");
}

#[test]
fn nan_value() {
    let text = GOOD.replace("command = { height_m = 0.8 }", "command = { height_m = nan }");
    assert_error(&text, "bad.toml:10:24: copter[0].command.height_m: must be finite, got NaN");
}

#[test]
fn overlapping_copters() {
    let text = GOOD.replace("pos_m = [1.0, 0.0]", "pos_m = [-0.8, 0.0]");
    assert_error(
        &text,
        "bad.toml:14:19: copter[1].start.pos_m: copter \"b\" overlaps copter \"a\": centres 0.200 m apart, need at least 0.327 m",
    );
}

#[test]
fn negative_size() {
    let text = GOOD.replace("size_m = [4.0, 3.0]", "size_m = [4.0, -3.0]");
    assert_error(&text, "bad.toml:4:10: arena.size_m: must be positive, got -3");
}

#[test]
fn control_step_not_a_multiple_of_physics_step() {
    let text = format!("[sim]\nphysics_dt_s = 0.004\ncontrol_dt_s = 0.05\n{GOOD}");
    let e = error_of(&text.replace("name = \"t\"\n", ""));
    assert_eq!(e.path().to_string(), "sim.control_dt_s", "{e}");
    assert_eq!(e.location().map(|l| l.line), Some(3), "{e}");
}

#[test]
fn unknown_airframe_preset_lists_the_known_ones() {
    let text = GOOD.replace("name = \"b\"", "name = \"b\"\nairframe = \"finken9\"");
    assert_error(
        &text,
        "bad.toml:14:12: copter[1].airframe: unknown airframe \"finken9\"; known: finken3, finken3_2015_12",
    );
}

#[test]
fn inline_airframe_override_is_checked() {
    let text = GOOD.replace("name = \"b\"", "name = \"b\"\nairframe = { body_mass_kg = -0.3 }");
    let e = error_of(&text);
    assert_eq!(e.path().to_string(), "copter[1].airframe.body_mass_kg", "{e}");
    assert_eq!(e.message(), "must be positive, got -0.3");
}

#[test]
fn firmware_height_loop_fields_are_checked() {
    let text = GOOD.replace("name = \"b\"", "name = \"b\"\nairframe = { finken_height = { rate_hz = 0.0 } }");
    let e = error_of(&text);
    assert_eq!(e.path().to_string(), "copter[1].airframe.finken_height.rate_hz", "{e}");
    assert_eq!(e.message(), "must be finite and positive, got 0");
    let text = GOOD.replace("name = \"b\"", "name = \"b\"\nairframe = { finken_height = { hover_gain = 1.0 } }");
    assert!(error_of(&text).to_string().contains("hover_gain"), "an unknown field is named");
}

#[test]
fn copter_inside_a_box() {
    let text = GOOD.replace(
        "[[copter]]\nname = \"a\"",
        "[[box]]\npos_m = [-1.0, 0.0]\nsize_m = [0.5, 0.5, 0.5]\n\n[[copter]]\nname = \"a\"",
    );
    let e = error_of(&text);
    assert_eq!(e.path().to_string(), "copter[0].start.pos_m", "{e}");
    assert!(e.message().contains("inside or touching box \"box0\""), "{e}");
}

#[test]
fn not_toml_at_all() {
    let e = error_of("this is [not toml");
    assert!(matches!(e, SceneError::Syntax { .. }), "{e}");
    assert_eq!(e.location().map(|l| l.line), Some(1), "{e}");
}

/// Every file under `assets/` that is a scene loads and compiles.
#[test]
fn every_scene_asset_loads() {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../assets/scenes");
    let mut n = 0;
    for entry in std::fs::read_dir(&dir).unwrap() {
        let path = entry.unwrap().path();
        if path.extension().is_some_and(|e| e == "toml") {
            let text = std::fs::read_to_string(&path).unwrap();
            if let Err(e) = scene::load(&path.display().to_string(), &text) {
                panic!("{e}");
            }
            n += 1;
        }
    }
    assert!(n >= 1, "no scenes found in {}", dir.display());
}

#[test]
fn the_embedded_default_is_the_shipped_lab_scene() {
    let shipped = std::fs::read_to_string(
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../assets/scenes/finken_lab.toml"),
    )
    .unwrap();
    assert_eq!(scene::DEFAULT_SCENE_TOML, shipped);
    let (spec, world) = scene::load_default();
    assert_eq!(world.arena.size_m, [4.0, 3.0]);
    assert_eq!(world.arena.height_m, 2.5);
    assert_eq!(world.copters.len(), 2);
    assert!(world.copters.iter().all(|c| c.initial_command.height_m == 0.8));
    assert!(!world.boxes.is_empty());
    // A spec survives a round trip through TOML.
    let again = sim_core::SceneSpec::from_toml("round-trip", &spec.to_toml()).unwrap();
    assert_eq!(again, spec);
}

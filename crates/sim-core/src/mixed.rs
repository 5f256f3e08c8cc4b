//! Mixed reality: what a twin's sonars see of the objects that exist only in the simulation.
//!
//! A real copter already sees the real lab with its own sonars. What it cannot see are the
//! **virtual** copters and the scene's `virtual_only` boxes. Its twin, flying in the
//! simulation at (about) the same pose, measures those for it; the real copter fuses them as
//! `min(real, virtual)`. The arena walls and ordinary boxes are in both worlds and are left
//! out here, and so are other twins (their real copters are physically there).
//!
//! The readings are noise-free distances (the real copter's sonar noise is its own), capped at
//! the sonar's maximum range: `INFINITY` means "nothing virtual in range".

use crate::math::Real;
use crate::scene::CopterKind;
use crate::sensors::{SonarScene, sonar_cones};
use crate::step::{GRID_CELL_M, copter_box};
use crate::{State, World};

/// Scratch for [`VirtualSonar::readings`]: the virtual-only geometry, gathered once per
/// sensing step with [`VirtualSonar::prepare`]. Reuses its buffers.
#[derive(Clone, Debug, Default)]
pub struct VirtualSonar {
    scene: SonarScene,
    /// World copter id of each entry of `scene.copters`, ascending.
    ids: Vec<usize>,
}

impl VirtualSonar {
    /// Gathers the virtual-only boxes and the virtual copters of the current state.
    pub fn prepare(&mut self, world: &World, state: &State) {
        let scene = &mut self.scene;
        scene.walls.clear();
        scene.boxes.clear();
        scene.boxes.extend(world.boxes.iter().filter(|b| b.virtual_only).map(|b| crate::geometry::OrientedBox {
            center: b.center_m,
            rotation: crate::math::Quat::from_rotation_z(b.yaw_rad),
            half: b.half_extents_m,
        }));
        scene.copters.clear();
        self.ids.clear();
        for (i, def) in world.copters.iter().enumerate() {
            if def.kind == CopterKind::Virtual {
                scene.copters.push(copter_box(world, &state.copters, i));
                self.ids.push(i);
            }
        }
        scene.index_copters(GRID_CELL_M);
    }

    /// Noise-free distances (front, right, back, left) from copter `i`'s sonars to the nearest
    /// virtual-only object in each cone, m; `INFINITY` when there is none within range. Call
    /// [`VirtualSonar::prepare`] first in the same state.
    pub fn readings(&self, world: &World, state: &State, i: usize) -> [Real; 4] {
        let m = &state.copters[i].motion;
        let cones = sonar_cones(&world.sensors, m.pos_m, m.rot);
        let range = world.sensors.spec.sonar.max_range_m;
        // A twin is not in the scene; a virtual copter asking must not see itself.
        let self_id = self.ids.binary_search(&i).unwrap_or(usize::MAX);
        cones.map(|cone| self.scene.cone_distance(&cone, self_id, range))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const SCENE: &str = r#"
name = "mr"
[arena]
size_m = [4.0, 3.0]
height_m = 2.5
[[box]]
name = "real_table"
pos_m = [-1.0, 0.0]
size_m = [0.4, 0.4, 1.0]
[[box]]
name = "ghost"
pos_m = [1.0, 0.0]
size_m = [0.4, 0.4, 1.0]
virtual_only = true
[[copter]]
name = "twin"
kind = "real"
ac_id = 5
start = { pos_m = [0.0, 0.0], z_m = 0.5 }
[[copter]]
name = "other"
kind = "virtual"
start = { pos_m = [0.0, 1.0], z_m = 0.5 }
"#;

    #[test]
    fn a_twin_sees_virtual_boxes_and_virtual_copters_but_not_walls_or_real_boxes() {
        let spec: crate::SceneSpec = toml::from_str(SCENE).unwrap();
        let world = crate::compile(&spec).unwrap();
        let state = world.initial_state();
        let mut vs = VirtualSonar::default();
        vs.prepare(&world, &state);
        let [front, right, back, left] = vs.readings(&world, &state, 0);
        // The ghost's near face is at x = 0.8; the sonar sits `mount_offset_m` ahead of the centre.
        let off = world.sensors.spec.sonar.mount_offset_m;
        assert!((front - (0.8 - off)).abs() < 1e-4, "front {front}");
        // Behind: only the real table and the wall, neither of which is virtual.
        assert!(back.is_infinite(), "back {back}");
        // Right (−y): the wall only.
        assert!(right.is_infinite(), "right {right}");
        // Left (+y): the virtual copter 1 m away, minus its half width.
        assert!(left.is_finite() && left < 1.0 && left > 0.7, "left {left}");
        // A virtual copter asking does not see itself, nor the twin (a real copter is really there).
        let other = vs.readings(&world, &state, 1);
        assert!(other[1].is_infinite(), "the twin is not a virtual object: {other:?}");
    }

    #[test]
    fn an_autopilot_copter_senses_the_real_layer_and_is_seen_by_virtual_copters() {
        // The twin of SCENE flown by an outside autopilot instead: physics moves it, and its own
        // sonars see what a real copter there would.
        let scene = SCENE.replace("kind = \"real\"", "kind = \"autopilot\"");
        let spec: crate::SceneSpec = toml::from_str(&scene).unwrap();
        let world = crate::compile(&spec).unwrap();
        assert_eq!(world.copters[0].initial_command.mode, crate::FlightMode::Rotors);
        let mut state = world.initial_state();
        let mut inputs = world.initial_inputs();
        inputs.commands[0].rotors = Some([0.5; 4]);
        // The firmware reads one sonar per update: four updates read them all.
        for _ in 0..4 * world.sensors.spec.sonar.period_steps {
            crate::step(&world, &mut state, &inputs);
        }
        let [front, right, back, left] = state.copters[0].sensors.sonar_truth_m;
        let hx = world.arena.size_m[0] / 2.0;
        // Front: not the virtual-only box at 0.8 m but the wall behind it.
        assert!(front > 1.5 && front <= hx, "front {front}");
        // Back: the real table, 0.8 m away.
        assert!(back < 1.0, "back {back}");
        // Left: not the virtual copter 1 m away, the wall 1.5 m away.
        assert!(left > 1.2, "left {left}");
        assert!(right > 1.2, "right {right}");
        // The virtual copter sees the autopilot's copter: it is as real to it as a twin.
        let seen = state.copters[1].sensors.sonar_truth_m[1];
        assert!(seen < 1.0, "the virtual copter's right sonar {seen}");
        // Virtual things reach it through the uplink, as they reach a real copter.
        let start = world.initial_state();
        let mut vs = VirtualSonar::default();
        vs.prepare(&world, &start);
        let [vf, _, _, vl] = vs.readings(&world, &start, 0);
        assert!(vf < 1.0 && vl < 1.0, "virtual sonar {vf} {vl}");
    }

    #[test]
    fn an_autopilot_copter_falls_through_a_virtual_only_box_and_onto_a_real_one() {
        // Two copters flown by an outside autopilot, motors off, 0.6 m above the tops of the real
        // table and of the virtual-only ghost: the real copter would fall through the ghost.
        let scene = SCENE
            .replace("kind = \"real\"", "kind = \"autopilot\"")
            .replace("start = { pos_m = [0.0, 0.0], z_m = 0.5 }", "start = { pos_m = [-1.0, 0.0], z_m = 1.6 }")
            .replace(
                "kind = \"virtual\"\nstart = { pos_m = [0.0, 1.0], z_m = 0.5 }",
                "kind = \"autopilot\"\nac_id = 6\nstart = { pos_m = [1.0, 0.0], z_m = 1.6 }",
            );
        let spec: crate::SceneSpec = toml::from_str(&scene).unwrap();
        let world = crate::compile(&spec).unwrap();
        assert!(world.copters.iter().all(|c| c.kind == CopterKind::Autopilot));
        let mut state = world.initial_state();
        let mut inputs = world.initial_inputs();
        for c in &mut inputs.commands {
            c.rotors = Some([0.0; 4]);
        }
        for _ in 0..(2.0 / world.params.control_dt_s).round() as u32 {
            crate::step(&world, &mut state, &inputs);
        }
        let (on_table, through_ghost) = (&state.copters[0], &state.copters[1]);
        assert!(on_table.motion.pos_m.z > 0.95, "stopped by the real table: {:?}", on_table.motion.pos_m);
        assert!(matches!(on_table.crash, Some(crate::CrashCause::Box { index: 0 }) | None), "{:?}", on_table.crash);
        assert!(through_ghost.motion.pos_m.z < 0.3, "fell through the ghost: {:?}", through_ghost.motion.pos_m);
        assert!(!matches!(through_ghost.crash, Some(crate::CrashCause::Box { .. })), "{:?}", through_ghost.crash);
    }
}

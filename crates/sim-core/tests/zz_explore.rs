//! TEMPORARY exploration harness (not to be committed).
use sim_core::{Event, step};

const LAB: &str = include_str!("../../../assets/scenes/finken_lab.toml");

fn scene(seed: u64, copters: usize, extra: &str) -> sim_core::World {
    let mut text = LAB.replace("seed = 2016", &format!("seed = {seed}"));
    if copters == 1 {
        let second = text.rfind("[[copter]]").unwrap();
        text.truncate(second);
    }
    text.push_str(extra);
    sim_core::scene::load("lab.toml", &text).unwrap_or_else(|e| panic!("{e}")).1
}

fn env<T: std::str::FromStr>(k: &str, d: T) -> T {
    std::env::var(k).ok().and_then(|v| v.parse().ok()).unwrap_or(d)
}

#[test]
fn explore() {
    let n: usize = env("N", 2);
    let secs: f64 = env("SECS", 300.0);
    let s0: u64 = env("S0", 1);
    let s1: u64 = env("S1", 10);
    let extra = std::env::var("EXTRA").unwrap_or_default().replace("\\n", "\n");
    for seed in s0..=s1 {
        let world = scene(seed, n, &extra);
        let mut state = world.initial_state();
        let inputs = world.initial_inputs();
        let ticks = (secs / world.params.control_dt_s) as u64;
        let mut min_wall = f32::MAX;
        let mut crash = None;
        let mut short = 0u64;
        let mut total = 0u64;
        let mut maxv: f32 = 0.0;
        let mut min_at = (0usize, sim_core::math::Vec3::ZERO);
        let (hx, hy) = (world.arena.size_m[0] / 2.0, world.arena.size_m[1] / 2.0);
        let t0 = std::time::Instant::now();
        for _ in 0..ticks {
            let r = step(&world, &mut state, &inputs);
            for e in &r.events {
                if let Event::Crashed { copter, cause } = e {
                    if crash.is_none() {
                        crash = Some((state.tick as f64 * 0.05, *copter, *cause));
                    }
                }
            }
            for i in 0..n {
                let p = state.pose(i);
                if state.copters[i].took_off_tick.is_some() && p.pos_m.z > 0.5 {
                    let mut d = (hx - p.pos_m.x.abs()).min(hy - p.pos_m.y.abs());
                    let mut what = 99;
                    for (bi, b) in world.boxes.iter().enumerate() {
                        let db = b.distance_to_point(p.pos_m);
                        if db < d { d = db; what = bi; }
                    }
                    if d < min_wall { min_wall = d; min_at = (what, p.pos_m); }
                    maxv = maxv.max(p.vel_m_s.truncate().length());
                }
                let s = &state.copters[i].sensors;
                for k in 0..4 {
                    total += 1;
                    if s.sonar_m[k] < s.sonar_truth_m[k] - 0.5 {
                        short += 1;
                    }
                }
            }
            if crash.is_some() && std::env::var("STOP").is_ok() {
                break;
            }
        }
        println!(
            "seed {seed:3}: min_wall {min_wall:.3} at {min_at:?} maxv {maxv:.2} short {:.4} crash {crash:?} ({:.1}s wall)",
            short as f64 / total as f64,
            t0.elapsed().as_secs_f64()
        );
    }
}

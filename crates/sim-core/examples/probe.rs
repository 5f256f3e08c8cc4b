// Exploration only (not committed).
use sim_core::*;
fn main() {
    let args: Vec<String> = std::env::args().collect();
    let extra = args.get(1).cloned().unwrap_or_default();
    let secs: f64 = args.get(2).map(|s| s.parse().unwrap()).unwrap_or(90.0);
    let seed = std::env::var("SEED").unwrap_or("2016".into());
    let text = std::fs::read_to_string(std::env::var("SCENE").unwrap_or("assets/scenes/finken_lab.toml".into()))
        .unwrap()
        .replace("seed = 2016", &format!("seed = {seed}"))
        + "\n"
        + &extra.replace("\\n", "\n");
    let quiet = std::env::var("QUIET").is_ok();
    let world = match scene::load("probe", &text) {
        Ok((_, w)) => w,
        Err(e) => panic!("{e}"),
    };
    let mut state = world.initial_state();
    let inputs = world.initial_inputs();
    let ticks = (secs / world.params.control_dt_s) as u64;
    let n = world.copters.len();
    let (mut zsum, mut zsq, mut cnt) = (vec![0.0f64; n], vec![0.0f64; n], 0u64);
    let mut minclear = vec![f64::MAX; n];
    let mut clear_sum = vec![0.0; n];
    let mut xt = 0u64;
    for t in 0..ticks {
        let rep = step(&world, &mut state, &inputs);
        for e in &rep.events {
            println!("t={:.2} {:?}", world.time_at(t), e);
        }
        if world.time_at(t) > 10.0 {
            cnt += 1;
            for i in 0..n {
                let p = state.pose(i).pos_m;
                zsum[i] += p.z as f64;
                zsq[i] += (p.z as f64).powi(2);
                let c = (2.0 - p.x.abs()).min(1.5 - p.y.abs()) as f64;
                minclear[i] = minclear[i].min(c);
                clear_sum[i] += c;
                xt += state.copters[i].sensors.sonar_crosstalk.iter().filter(|&&x| x).count() as u64;
            }
        }
        if std::env::var("TRACE").is_ok()
            && world.time_at(t) >= std::env::var("TRACE").unwrap().parse::<f64>().unwrap()
            && world.time_at(t) < std::env::var("TRACE").unwrap().parse::<f64>().unwrap() + 8.0
        {
            for i in 0..n {
                let c = &state.copters[i];
                let p = state.pose(i);
                println!(
                    "t={:.2} c{i} pos=({:.2},{:.2},{:.2}) rpy=({:.3},{:.3}) sp=({:.3},{:.3}) son={:?} xt={:?} hest={:.2}",
                    world.time_at(t),
                    p.pos_m.x,
                    p.pos_m.y,
                    p.pos_m.z,
                    p.rpy_rad[0],
                    p.rpy_rad[1],
                    c.setpoint.roll_rad,
                    c.setpoint.pitch_rad,
                    c.sensors.sonar_fused_m,
                    c.sensors.sonar_crosstalk,
                    c.estimate.height_m
                );
            }
        }
        if t % 1200 == 0 && !quiet {
            for i in 0..n {
                let c = &state.copters[i];
                println!(
                    "t={:.0} c{i} pos={:?} hest={:.3} V={:.2} I={:.2} soc={:.3} gain={:.3} integ={:.3}",
                    world.time_at(t),
                    state.pose(i).pos_m,
                    c.estimate.height_m,
                    c.battery.voltage_v,
                    c.battery.current_a,
                    c.battery.charge,
                    c.estimate.thrust_gain,
                    c.estimate.height_integral_n
                );
            }
        }
    }
    for i in 0..n {
        let m = zsum[i] / cnt as f64;
        let sd = (zsq[i] / cnt as f64 - m * m).sqrt();
        println!(
            "c{i}: z mean {m:.3} sd {sd:.3} clearance mean {:.2} min {:.2} crash {:?}",
            clear_sum[i] / cnt as f64,
            minclear[i],
            state.copters[i].crash
        );
    }
    println!("crosstalk readings {xt}");
}

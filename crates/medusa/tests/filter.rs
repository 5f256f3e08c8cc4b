//! The particle filter: convergence, determinism, degenerate cases, errors.

mod common;

use common::{gauss, medusa, noisy_readings, true_ranges};
use medusa::{FilterConfig, FilterEstimate, MedusaError, MedusaFilter, MotionInput, YawEstimate};
use nalgebra::Vector2;
use rand::SeedableRng;
use rand_pcg::Pcg64;

const DT_S: f64 = 0.05;

fn assert_sane(e: &FilterEstimate) {
    assert!(e.pos_in_world.iter().all(|v| v.is_finite()));
    assert!(e.covariance_m2.iter().all(|v| v.is_finite()));
    assert!(e.vel_in_world_mps.iter().all(|v| v.is_finite()));
    assert!((0.0..=1.0).contains(&e.confidence));
    assert!(e.yaw_bias_rad.is_finite() && e.yaw_bias_sigma_rad.is_finite());
}

/// Hover at `pos` with yaw `yaw` for `steps` cycles with noisy readings and
/// a constant yaw bias; returns the final estimate.
fn hover(
    filter: &mut MedusaFilter,
    pos: Vector2<f64>,
    yaw: f64,
    bias_rad: f64,
    steps: usize,
    seed: u64,
) -> FilterEstimate {
    let mut rng = Pcg64::seed_from_u64(seed);
    let m = filter.medusa().clone();
    let mut est = filter.estimate();
    for _ in 0..steps {
        let ranges = true_ranges(m.world(), m.layout(), pos, yaw, 15f64.to_radians());
        let readings = noisy_readings(&ranges, 0.05, &mut rng);
        let yaw_est = YawEstimate::new(yaw + bias_rad + 2f64.to_radians() * gauss(&mut rng), 0.035);
        est = filter.update(DT_S, &MotionInput::zero(), yaw_est, &readings).expect("update");
        assert_sane(&est);
    }
    est
}

#[test]
fn converges_from_a_wrong_start() {
    let mut filter = MedusaFilter::new(medusa(4, vec![]), FilterConfig::default()).expect("filter");
    filter.reset_at(Vector2::new(-1.5, -1.0), 0.05).expect("reset");
    let truth = Vector2::new(1.2, 0.7);
    // Wrong start, oblique yaw and a 6° yaw bias.
    let est = hover(&mut filter, truth, 0.6, 6f64.to_radians(), 100, 7);
    let err = (est.pos_in_world - truth).norm();
    assert!(err < 0.05, "error after 5 s: {err} m");
    assert!(est.confidence > 0.5, "confidence {}", est.confidence);
    assert!(
        (est.yaw_bias_rad - 6f64.to_radians()).abs() < 3f64.to_radians(),
        "yaw bias {}°",
        est.yaw_bias_rad.to_degrees()
    );
}

#[test]
fn converges_from_uniform_start() {
    let mut filter = MedusaFilter::new(medusa(4, vec![]), FilterConfig::default()).expect("filter");
    assert!(filter.estimate().confidence < 0.2);
    let truth = Vector2::new(-0.4, 1.0);
    let est = hover(&mut filter, truth, -0.2, 0.0, 40, 8);
    assert!((est.pos_in_world - truth).norm() < 0.05);
    assert!(est.confidence > 0.5);
}

#[test]
fn is_deterministic_for_a_seed() {
    let run = |seed: u64| {
        let mut f =
            MedusaFilter::new(medusa(4, vec![]), FilterConfig { seed, ..FilterConfig::default() }).expect("filter");
        hover(&mut f, Vector2::new(0.3, 0.2), 0.4, 0.0, 20, 9)
    };
    assert_eq!(run(1), run(1));
    assert_ne!(run(1).pos_in_world, run(2).pos_in_world);
}

#[test]
fn degenerate_cases_are_low_confidence_not_panics() {
    let yaw = YawEstimate::new(0.2, 0.03);
    // All readings out of range, from the start.
    let mut f = MedusaFilter::new(medusa(4, vec![]), FilterConfig::default()).expect("filter");
    for _ in 0..40 {
        let e = f.update(DT_S, &MotionInput::zero(), yaw, &[None; 4]).expect("update");
        assert_sane(&e);
    }
    assert!(f.estimate().confidence < 0.1, "conf {}", f.estimate().confidence);

    // All readings out of range after a good fix: confidence decays.
    let mut f = MedusaFilter::new(medusa(4, vec![]), FilterConfig::default()).expect("filter");
    let good = hover(&mut f, Vector2::new(0.5, 0.5), 0.2, 0.0, 40, 10);
    assert!(good.confidence > 0.5);
    for _ in 0..40 {
        let e = f.update(DT_S, &MotionInput::zero(), yaw, &[None; 4]).expect("update");
        assert_sane(&e);
    }
    assert!(f.estimate().confidence < 0.2, "conf {}", f.estimate().confidence);

    // Two opposite sensors: y is unobservable in the middle of the arena.
    let specs = [0.0f64, 180.0]
        .iter()
        .map(|d| medusa::SensorSpec {
            angle_in_body_rad: d.to_radians(),
            offset_in_body_m: Vector2::zeros(),
            max_range_m: 3.0,
        })
        .collect();
    let m2 = medusa::Medusa::new(
        medusa(4, vec![]).world().clone(),
        medusa::SensorLayout::new(specs).expect("layout"),
        medusa::SensorModel::default(),
    )
    .expect("medusa");
    let mut f = MedusaFilter::new(m2, FilterConfig::default()).expect("filter");
    let e = hover(&mut f, Vector2::new(0.3, 0.0), 0.0, 0.0, 60, 11);
    assert!(e.confidence < 0.3, "conf {}", e.confidence);
    assert!(e.covariance_m2[(1, 1)] > 0.05);

    // Two perpendicular sensors: works, no panic.
    let mut f = MedusaFilter::new(medusa(2, vec![]), FilterConfig::default()).expect("filter");
    let e = hover(&mut f, Vector2::new(0.8, 0.4), 0.1, 0.0, 60, 12);
    assert_sane(&e);

    // In a corner, pointing into it.
    let mut f = MedusaFilter::new(medusa(4, vec![]), FilterConfig::default()).expect("filter");
    let corner = Vector2::new(1.85, 1.35);
    let e = hover(&mut f, corner, 45f64.to_radians(), 0.0, 60, 13);
    let err = (e.pos_in_world - corner).norm();
    assert!(err < 0.1 || e.confidence < 0.5, "corner err {err}, conf {}", e.confidence);
}

#[test]
fn bad_inputs_are_typed_errors_and_leave_the_state_intact() {
    let mut f = MedusaFilter::new(medusa(4, vec![]), FilterConfig::default()).expect("filter");
    let before = f.particles();
    let yaw = YawEstimate::new(0.0, 0.03);
    let zero = MotionInput::zero();
    assert!(matches!(
        f.update(DT_S, &zero, yaw, &[Some(f64::NAN), None, None, None]),
        Err(MedusaError::InvalidReading { .. })
    ));
    assert!(matches!(f.update(DT_S, &zero, yaw, &[None; 3]), Err(MedusaError::ReadingCount { .. })));
    assert!(matches!(f.update(-1.0, &zero, yaw, &[None; 4]), Err(MedusaError::InvalidParameter { name: "dt_s", .. })));
    assert!(matches!(f.update(f64::NAN, &zero, yaw, &[None; 4]), Err(MedusaError::InvalidParameter { .. })));
    assert!(matches!(
        f.update(DT_S, &MotionInput::from_attitude(f64::NAN, 0.0), yaw, &[None; 4]),
        Err(MedusaError::InvalidParameter { .. })
    ));
    assert!(matches!(
        f.update(DT_S, &zero, YawEstimate::new(f64::INFINITY, 0.0), &[None; 4]),
        Err(MedusaError::InvalidYaw { .. })
    ));
    assert_eq!(before, f.particles());
    assert!(f.reset_at(Vector2::new(f64::NAN, 0.0), 0.1).is_err());
    assert!(f.reset_at(Vector2::zeros(), -0.1).is_err());
    assert!(
        MedusaFilter::new(medusa(4, vec![]), FilterConfig { num_particles: 0, ..FilterConfig::default() }).is_err()
    );
}

#[test]
fn motion_model_follows_the_commanded_attitude() {
    // Positive pitch accelerates forward; with yaw 90° forward is world +y.
    let a = MotionInput::from_attitude(5f64.to_radians(), 0.0);
    assert!(a.accel_in_body_mps2.x > 0.8 && a.accel_in_body_mps2.y.abs() < 1e-12);
    let r = MotionInput::from_attitude(0.0, 5f64.to_radians());
    assert!(r.accel_in_body_mps2.y < -0.8);

    let mut f = MedusaFilter::new(
        medusa(4, vec![]),
        FilterConfig {
            velocity_noise_mps_per_sqrt_s: 0.0,
            position_noise_m_per_sqrt_s: 0.0,
            yaw_bias_noise_rad_per_sqrt_s: 0.0,
            initial_yaw_bias_sigma_rad: 0.0,
            drag_per_s: 0.0,
            ..FilterConfig::default()
        },
    )
    .expect("filter");
    f.reset_at(Vector2::zeros(), 0.0).expect("reset");
    let yaw = YawEstimate::new(std::f64::consts::FRAC_PI_2, 0.0);
    for _ in 0..10 {
        f.predict(0.05, &a, yaw).expect("predict");
    }
    let p = f.particles()[0];
    // 0.5 * a * t^2 with t = 0.5 s.
    let expect = 0.5 * a.accel_in_body_mps2.x * 0.25;
    assert!(p.pos_in_world.x.abs() < 1e-9);
    assert!((p.pos_in_world.y - expect).abs() < 1e-9, "{:?}", p.pos_in_world);
}

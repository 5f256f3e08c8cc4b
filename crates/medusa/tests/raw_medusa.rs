//! Raw MEDUSA: exact recovery, ambiguity handling, degenerate cases, errors.

mod common;

use common::{MAX_RANGE_M, arena, exact_readings, medusa, true_ranges};
use medusa::{Arena, BoxObstacle, Medusa, MedusaError, SensorLayout, SensorModel, SensorSpec, World, YawEstimate};
use nalgebra::Vector2;

fn poses() -> Vec<(Vector2<f64>, f64)> {
    vec![
        (Vector2::new(0.0, 0.0), 0.0),
        (Vector2::new(0.7, -0.4), 0.1),
        (Vector2::new(-1.3, 0.9), -0.5),
        (Vector2::new(1.6, 1.1), 0.8),
        (Vector2::new(-0.2, -1.2), 2.5),
        (Vector2::new(1.2, -0.3), 45f64.to_radians()),
        (Vector2::new(-1.7, -1.2), -2.0),
    ]
}

#[test]
fn exact_readings_give_the_pose_back() {
    for n in [2usize, 3, 4, 8] {
        for cone_deg in [0.0f64, 15.0] {
            let model = SensorModel { cone_half_angle_rad: cone_deg.to_radians(), ..SensorModel::default() };
            let base = medusa(n, vec![]);
            let m = Medusa::new(base.world().clone(), base.layout().clone(), model).expect("medusa");
            for (pos, yaw) in poses() {
                // Independent brute-force fan (exact for plane walls).
                let ranges = true_ranges(m.world(), m.layout(), pos, yaw, cone_deg.to_radians());
                let readings = exact_readings(&ranges);
                let in_range = readings.iter().filter(|r| r.is_some()).count();
                let res = m.locate(YawEstimate::new(yaw, 0.0), &readings).expect("locate");
                let err = (res.refined.pos_in_world - pos).norm();
                if n >= 4 || (in_range == n && !res.ambiguous) {
                    assert!(
                        err < 1e-3,
                        "n={n} cone={cone_deg} pose={pos:?} yaw={yaw}: error {err} m, best {:?}",
                        res.best.pos_in_world
                    );
                    assert!(res.confidence > 0.5, "confidence {}", res.confidence);
                }
                assert!(res.confidence.is_finite());
            }
        }
    }
}

#[test]
fn exact_readings_near_boxes_give_the_pose_back() {
    let boxes = vec![
        BoxObstacle::axis_aligned(Vector2::new(0.9, 0.6), Vector2::new(0.2, 0.2)),
        BoxObstacle::new(Vector2::new(-0.8, -0.5), Vector2::new(0.25, 0.15), 0.5),
    ];
    let m = medusa(4, boxes);
    for (pos, yaw) in [
        (Vector2::new(0.4, 0.6), 0.05),
        (Vector2::new(0.9, 0.1), 1.2),
        (Vector2::new(-0.3, -0.6), -0.3),
        (Vector2::new(-0.8, 0.1), 0.4),
    ] {
        assert!(m.world().is_free(&pos, 0.1));
        let ranges = m.predict_ranges_m(&pos, yaw);
        let res = m.locate(YawEstimate::new(yaw, 0.0), &exact_readings(&ranges)).expect("locate");
        let err = (res.refined.pos_in_world - pos).norm();
        assert!(err < 1e-3, "pose {pos:?} yaw {yaw}: error {err}");
    }
}

#[test]
fn point_symmetry_is_resolved_by_yaw() {
    // A symmetric 4-sonar ring at (p, yaw) and at (-p, yaw + pi) sees exactly
    // the same readings; the yaw estimate picks the right one.
    let m = medusa(4, vec![]);
    let pos = Vector2::new(1.0, 0.5);
    let yaw = 0.2;
    let readings = exact_readings(&m.predict_ranges_m(&pos, yaw));
    let mirrored = exact_readings(&m.predict_ranges_m(&-pos, yaw + std::f64::consts::PI));
    for (a, b) in readings.iter().zip(&mirrored) {
        match (a, b) {
            (Some(a), Some(b)) => assert!((a - b).abs() < 1e-9),
            (None, None) => {}
            _ => panic!("readings differ"),
        }
    }
    let r1 = m.locate(YawEstimate::new(yaw, 0.03), &readings).expect("locate");
    assert!((r1.refined.pos_in_world - pos).norm() < 1e-3);
    let r2 = m.locate(YawEstimate::new(yaw + std::f64::consts::PI, 0.03), &readings).expect("locate");
    assert!((r2.refined.pos_in_world + pos).norm() < 1e-3);
    assert!(!r1.ambiguous && !r2.ambiguous);
}

#[test]
fn unresolvable_symmetry_is_reported_as_ambiguous() {
    // Two opposite sonars along x: y is not observable (away from walls).
    let specs = [0.0f64, 180.0]
        .iter()
        .map(|d| SensorSpec {
            angle_in_body_rad: d.to_radians(),
            offset_in_body_m: Vector2::zeros(),
            max_range_m: MAX_RANGE_M,
        })
        .collect();
    let layout = SensorLayout::new(specs).expect("layout");
    let m = Medusa::new(World::empty(arena()), layout, SensorModel::default()).expect("medusa");
    let pos = Vector2::new(0.3, 0.2);
    let res = m.locate(YawEstimate::new(0.0, 0.01), &exact_readings(&m.predict_ranges_m(&pos, 0.0))).expect("locate");
    assert!(res.ambiguous);
    assert!(res.modes.len() > 1);
    assert!(res.confidence < 0.3, "confidence {}", res.confidence);
    // x is still right.
    assert!((res.refined.pos_in_world.x - pos.x).abs() < 1e-3);

    // Short-range sonars near the east wall: only the front one sees a wall,
    // so the copter could be anywhere along a band in y.
    let short =
        Medusa::new(World::empty(arena()), SensorLayout::ring(4, 0.08, 1.0).expect("layout"), SensorModel::default())
            .expect("medusa");
    let pos = Vector2::new(1.5, 0.1);
    let res2 =
        short.locate(YawEstimate::new(0.0, 0.03), &exact_readings(&short.predict_ranges_m(&pos, 0.0))).expect("locate");
    assert!(res2.ambiguous && res2.underdetermined);
    assert!(res2.confidence < 0.3, "confidence {}", res2.confidence);
    assert!((res2.refined.pos_in_world.x - pos.x).abs() < 1e-3);
}

fn check_finite(res: &medusa::MedusaResult) {
    assert!(res.best.pos_in_world.iter().all(|v| v.is_finite()));
    assert!(res.refined.pos_in_world.iter().all(|v| v.is_finite()));
    assert!((0.0..=1.0).contains(&res.confidence));
    assert!(res.candidates.iter().all(|c| c.probability.is_finite()));
}

#[test]
fn degenerate_cases_are_low_confidence_not_panics() {
    let m = medusa(4, vec![]);
    // All readings out of range (impossible in a 4 x 3 arena with 3 m sonars).
    let res = m.locate(YawEstimate::new(0.3, 0.03), &[None, None, None, None]).expect("locate");
    check_finite(&res);
    assert!(res.underdetermined && res.ambiguous);
    assert!(res.confidence < 0.1, "confidence {}", res.confidence);

    // Two sensors only, one of them out of range.
    let m2 = medusa(2, vec![]);
    let res = m2.locate(YawEstimate::new(0.0, 0.03), &[Some(1.0), None]).expect("locate");
    check_finite(&res);
    assert!(res.confidence < 0.3);
    // Two sensors, both in range: fine.
    let pos = Vector2::new(0.5, 0.2);
    let res = m2.locate(YawEstimate::new(0.1, 0.0), &exact_readings(&m2.predict_ranges_m(&pos, 0.1))).expect("locate");
    check_finite(&res);

    // In a corner, pointing into it.
    for yaw in [0.0f64, 45f64.to_radians(), -135f64.to_radians()] {
        let pos = Vector2::new(1.88, 1.38);
        let ranges = m.predict_ranges_m(&pos, yaw);
        let res = m.locate(YawEstimate::new(yaw, 0.03), &exact_readings(&ranges)).expect("locate");
        check_finite(&res);
        let err = (res.refined.pos_in_world - pos).norm();
        assert!(err < 0.05 || res.confidence < 0.5, "corner err {err}");
    }
    // Readings all zero: only consistent with the body centre squeezed into
    // one of the four corners, which is reported as ambiguous.
    let res = m.locate(YawEstimate::new(0.0, 0.03), &[Some(0.0); 4]).expect("locate");
    check_finite(&res);
    assert!(res.ambiguous && res.confidence < 0.3);
}

#[test]
fn bad_inputs_are_typed_errors() {
    let m = medusa(4, vec![]);
    let yaw = YawEstimate::new(0.0, 0.03);
    assert!(matches!(
        m.locate(yaw, &[Some(f64::NAN), None, None, None]),
        Err(MedusaError::InvalidReading { index: 0, .. })
    ));
    assert!(matches!(
        m.locate(yaw, &[None, Some(-1.0), None, None]),
        Err(MedusaError::InvalidReading { index: 1, .. })
    ));
    assert!(matches!(m.locate(yaw, &[None, None]), Err(MedusaError::ReadingCount { expected: 4, got: 2 })));
    assert!(matches!(m.locate(YawEstimate::new(f64::NAN, 0.0), &[None; 4]), Err(MedusaError::InvalidYaw { .. })));
    assert!(matches!(m.locate(YawEstimate::new(0.0, -1.0), &[None; 4]), Err(MedusaError::InvalidYaw { .. })));
    assert!(matches!(SensorLayout::new(vec![]), Err(MedusaError::SensorCount { count: 0, .. })));
    assert!(matches!(Arena::new(0.0, 3.0), Err(MedusaError::InvalidArena { .. })));
    assert!(matches!(Arena::new(4.0, -3.0), Err(MedusaError::InvalidArena { .. })));
    assert!(matches!(
        World::new(arena(), vec![BoxObstacle::axis_aligned(Vector2::zeros(), Vector2::new(0.0, 1.0))]),
        Err(MedusaError::InvalidObstacle { index: 0, .. })
    ));
    assert!(matches!(
        Medusa::new(
            World::empty(arena()),
            SensorLayout::ring(4, 0.1, 3.0).expect("layout"),
            SensorModel { noise_sigma_m: 0.0, ..SensorModel::default() }
        ),
        Err(MedusaError::InvalidParameter { .. })
    ));
}

#[test]
fn huge_arena_stays_bounded() {
    let m = Medusa::new(
        World::empty(Arena::new(1e12, 1e9).expect("arena")),
        SensorLayout::ring(4, 0.08, 3.0).expect("layout"),
        SensorModel::default(),
    )
    .expect("medusa");
    let res = m.locate(YawEstimate::new(1e6, 0.03), &[None, Some(1.0), None, None]).expect("locate");
    check_finite(&res);
    assert!(res.candidates.len() <= medusa::MAX_CANDIDATES);
}

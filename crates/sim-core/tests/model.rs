//! The derived rotor model against hand calculations, including the report's own numbers.

mod common;

fn close(got: f32, want: f64, rel: f64, what: &str) {
    let err = ((got as f64 - want) / want).abs();
    assert!(err < rel, "{what}: got {got}, hand calculation {want} (relative error {err:.2e})");
}

/// FINken III defaults: body 0.296 kg + 4 × 0.025 kg, 0.1274 m discs, ρ = 1.2041 kg/m³.
///
/// By hand (a calculator, step by step):
/// - m = 0.296 + 4 · 0.025 = 0.396 kg; F = 0.396 · 9.81 / 4 = 0.97119 N
/// - A = π/4 · 0.1274² = 0.785398 · 0.01623076 = 0.01274761 m²
/// - v_rotor = sqrt(0.97119 / (2 · 1.2041 · 0.01274761)) = sqrt(31.63609) = 5.624598 m/s
/// - v_final = 2 · 5.624598 = 11.249195 m/s
/// - ṁ = F / v_final = 0.97119 / 11.249195 = 0.08633418 kg/s
/// - m_px = ṁ / 430 = 2.007772e-4 kg
/// - V_px = π/6 · 0.005³ = 6.544985e-8 m³; ρ_px = m_px / V_px = 3067.649 kg/m³
/// - ṅ / v_final = ρ A / (2 m_px) = 0.01534944 / 4.015543e-4 = 38.22496 1/m (× v_final = 430 /s)
/// - Ixx = 0.296/12 · (0.10² + 0.04²) + 4 · 0.025 · 0.1²/2 = 2.861333e-4 + 5.0e-4 = 7.861333e-4 kg m²
/// - Izz = 0.296/12 · (0.10² + 0.10²) + 4 · 0.025 · 0.1² = 4.933333e-4 + 1.0e-3 = 1.493333e-3 kg m²
#[test]
fn finken3_rotor_numbers_match_a_hand_calculation() {
    let world = common::one_copter_scene("", "");
    let af = &world.airframes[0];
    close(af.mass_kg, 0.396, 1e-6, "mass");
    close(af.hover_thrust_per_rotor_n, 0.97119, 1e-5, "hover thrust");
    close(af.disc_area_m2, 0.01274761, 1e-5, "disc area");
    close(af.v_rotor_m_s, 5.624598, 1e-5, "v_rotor");
    close(af.v_final_m_s, 11.249195, 1e-5, "v_final");
    close(af.mass_flow_kg_s, 0.08633418, 1e-5, "mass flow");
    close(af.particle_mass_kg, 2.007772e-4, 1e-5, "particle mass");
    close(af.particle_density_kg_m3, 3067.649, 1e-5, "particle density");
    close(af.particle_rate_per_v_final_per_m, 38.22496, 1e-5, "ṅ/v_final");
    close(af.particle_rate_per_v_final_per_m * af.v_final_m_s, 430.0, 1e-5, "ṅ at hover");
    close(af.inertia_kg_m2[0], 7.861333e-4, 1e-5, "Ixx");
    close(af.inertia_kg_m2[1], 7.861333e-4, 1e-5, "Iyy");
    close(af.inertia_kg_m2[2], 1.493333e-3, 1e-5, "Izz");
    // Mean thrust k ω² at the hover speed is the hover thrust.
    close(af.thrust_at(af.omega_hover_rad_s), 0.97119, 1e-5, "k ω_hover²");
}

/// The report's own worked example (eq. 3.1–3.4): 0.096 kg per rotor, i.e. a 0.384 kg copter.
/// v_final = 11.0774 m/s, m_px = 1.9771e-4 kg, ρ_px = 3020.8119 kg/m³, ṅ = 38.8180 /m · v_final.
#[test]
fn the_reports_worked_example_is_reproduced() {
    let world = common::one_copter_scene("", "airframe = { body_mass_kg = 0.284 }");
    let af = &world.airframes[0];
    close(af.mass_kg, 0.384, 1e-6, "mass");
    close(af.v_final_m_s, 11.0774, 1e-4, "v_final (eq. 3.1)");
    close(af.particle_mass_kg, 1.9771e-4, 1e-4, "m_px (eq. 3.2)");
    close(af.particle_density_kg_m3, 3020.8119, 1e-4, "ρ_px (eq. 3.3)");
    close(af.particle_rate_per_v_final_per_m, 38.8180, 1e-4, "ṅ/v_final (eq. 3.4)");
}

/// The mean thrust with particle noise on equals k ω² (the particle model is unbiased).
#[test]
fn particle_noise_is_unbiased() {
    use sim_core::airframe::ParticleNoise;
    for noise in ["dither", "poisson"] {
        let world = common::one_copter_scene(
            "",
            &format!(
                "airframe = {{ particle_noise = \"{noise}\", rotor_tolerance_sigma = 0.0 }}\ncommand = {{ height_m = 1.0 }}"
            ),
        );
        assert_ne!(world.airframes[0].spec.particle_noise, ParticleNoise::Off);
        let mut state = world.initial_state();
        let inputs = world.initial_inputs();
        let (mut sum_thrust, mut sum_mean, mut n) = (0.0f64, 0.0f64, 0);
        for _ in 0..2000 {
            sim_core::step(&world, &mut state, &inputs);
            let c = &state.copters[0];
            for r in 0..4 {
                sum_thrust += c.rotor_thrust_n[r] as f64;
                sum_mean += world.airframes[0].thrust_at(c.rotor_speed_rad_s[r]) as f64;
                n += 1;
            }
        }
        let bias = (sum_thrust - sum_mean) / sum_mean;
        println!(
            "{noise}: mean thrust {:.4} N vs k ω² {:.4} N (bias {:.2} %)",
            sum_thrust / n as f64,
            sum_mean / n as f64,
            bias * 100.0
        );
        assert!(bias.abs() < 0.03, "{noise}: bias {bias}");
    }
}

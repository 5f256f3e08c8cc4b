//! Math types and the frame conventions every other module relies on.
//!
//! **Frames.** The world frame is ENU-like: `x` along the arena's long side, `y` across it, `z`
//! up, origin at the centre of the arena floor. The body frame is FLU (REP-103): `x` forward,
//! `y` left, `z` up. Attitude is ZYX Euler (`yaw`, then `pitch`, then `roll`), so:
//! - `roll_rad > 0` lowers the right side: the copter accelerates towards body `-y` (right);
//! - `pitch_rad > 0` lowers the nose: the copter accelerates towards body `+x` (forward);
//! - `yaw_rad` is counter-clockwise from world `+x`, seen from above.
//!
//! Paparazzi uses NED/FRD: the bridge converts at the edge, never here.

pub use rapier3d::glamx::{Quat, Vec2, Vec3};
pub use rapier3d::math::{Real, Vector};

/// Standard gravity, m/s².
pub const GRAVITY_M_S2: Real = 9.81;

/// Wraps an angle into (−π, π].
#[inline]
pub fn wrap_angle_rad(a: Real) -> Real {
    use std::f32::consts::{PI, TAU};
    if a > -PI && a <= PI {
        return a; // already wrapped: the common case, exact and cheap
    }
    let mut w = a.rem_euclid(TAU);
    if w > PI {
        w -= TAU;
    }
    w
}

/// Roll, pitch, yaw (ZYX Euler, radians) of a world-from-body rotation.
#[inline]
pub fn euler_from_quat(q: Quat) -> [Real; 3] {
    let (x, y, z, w) = (q.x, q.y, q.z, q.w);
    let sinr_cosp = 2.0 * (w * x + y * z);
    let cosr_cosp = 1.0 - 2.0 * (x * x + y * y);
    let roll = sinr_cosp.atan2(cosr_cosp);
    let sinp = (2.0 * (w * y - z * x)).clamp(-1.0, 1.0);
    let pitch = sinp.asin();
    let siny_cosp = 2.0 * (w * z + x * y);
    let cosy_cosp = 1.0 - 2.0 * (y * y + z * z);
    let yaw = siny_cosp.atan2(cosy_cosp);
    [roll, pitch, yaw]
}

/// World-from-body rotation from roll, pitch, yaw (ZYX Euler, radians).
#[inline]
pub fn quat_from_euler(roll_rad: Real, pitch_rad: Real, yaw_rad: Real) -> Quat {
    Quat::from_rotation_z(yaw_rad) * Quat::from_rotation_y(pitch_rad) * Quat::from_rotation_x(roll_rad)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn wrap_angle_stays_in_half_open_interval() {
        use std::f32::consts::PI;
        assert!((wrap_angle_rad(3.0 * PI) - PI).abs() < 1e-5);
        assert!((wrap_angle_rad(-PI) - PI).abs() < 1e-5);
        assert!((wrap_angle_rad(0.5) - 0.5).abs() < 1e-6);
        assert!((wrap_angle_rad(-0.5 - 2.0 * PI) + 0.5).abs() < 1e-5);
    }

    #[test]
    fn euler_round_trip() {
        let q = quat_from_euler(0.1, -0.2, 2.5);
        let [r, p, y] = euler_from_quat(q);
        assert!((r - 0.1).abs() < 1e-5 && (p + 0.2).abs() < 1e-5 && (y - 2.5).abs() < 1e-5);
    }

    #[test]
    fn positive_pitch_tilts_thrust_forward() {
        let thrust_dir = quat_from_euler(0.0, 0.2, 0.0) * Vec3::Z;
        assert!(thrust_dir.x > 0.1, "pitch > 0 must accelerate towards +x, got {thrust_dir:?}");
        let thrust_dir = quat_from_euler(0.2, 0.0, 0.0) * Vec3::Z;
        assert!(thrust_dir.y < -0.1, "roll > 0 must accelerate towards -y (right), got {thrust_dir:?}");
    }
}

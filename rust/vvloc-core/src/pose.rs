//! SE(2) poses and the relative-pose convention of DESIGN.md §3.
//!
//! A pose is (x, y, yaw): metres, metres, radians, yaw counter-clockwise positive about z.
//! The relative pose ξ_{s→t} is the target frame expressed in the source frame:
//! `T_world_t = T_world_s · ξ`.

use nalgebra::{Isometry2, Vector2};
use std::f64::consts::PI;

/// Wraps an angle in radians to (−π, π].
pub fn wrap_angle(a: f64) -> f64 {
    let mut w = a.rem_euclid(2.0 * PI); // [0, 2π)
    if w > PI {
        w -= 2.0 * PI;
    }
    w
}

/// A 3-DoF pose (x, y in metres, yaw in radians).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Pose2 {
    pub x: f64,
    pub y: f64,
    pub yaw: f64,
}

impl Pose2 {
    /// Builds a pose; `yaw` is wrapped to (−π, π].
    pub fn new(x: f64, y: f64, yaw: f64) -> Self {
        Pose2 {
            x,
            y,
            yaw: wrap_angle(yaw),
        }
    }

    fn iso(&self) -> Isometry2<f64> {
        Isometry2::new(Vector2::new(self.x, self.y), self.yaw)
    }

    fn from_iso(iso: &Isometry2<f64>) -> Self {
        Pose2::new(
            iso.translation.vector.x,
            iso.translation.vector.y,
            iso.rotation.angle(),
        )
    }

    /// Composition `self · other` (apply `other` in `self`'s frame).
    pub fn compose(&self, other: &Pose2) -> Pose2 {
        Pose2::from_iso(&(self.iso() * other.iso()))
    }

    /// Inverse pose.
    pub fn inverse(&self) -> Pose2 {
        Pose2::from_iso(&self.iso().inverse())
    }

    /// ξ_{s→t} = T_world_s⁻¹ · T_world_t, with `self` = source, `target` = target.
    pub fn relative_to(&self, target: &Pose2) -> Pose2 {
        self.inverse().compose(target)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn wrap_is_half_open() {
        assert!((wrap_angle(PI) - PI).abs() < 1e-12);
        assert!((wrap_angle(-PI) - PI).abs() < 1e-12);
        assert!((wrap_angle(3.0 * PI / 2.0) + PI / 2.0).abs() < 1e-12);
        assert_eq!(wrap_angle(0.0), 0.0);
    }

    #[test]
    fn relative_pose_roundtrip() {
        let s = Pose2::new(1.0, 2.0, 0.3);
        let t = Pose2::new(-0.5, 4.0, -2.9);
        let xi = s.relative_to(&t);
        let t2 = s.compose(&xi);
        assert!((t2.x - t.x).abs() < 1e-12 && (t2.y - t.y).abs() < 1e-12);
        assert!(wrap_angle(t2.yaw - t.yaw).abs() < 1e-12);
    }

    #[test]
    fn target_origin_in_source_frame() {
        // Source at origin facing +y (yaw 90°); a target 1 m north is 1 m ahead (x forward).
        let s = Pose2::new(0.0, 0.0, PI / 2.0);
        let t = Pose2::new(0.0, 1.0, PI / 2.0);
        let xi = s.relative_to(&t);
        assert!((xi.x - 1.0).abs() < 1e-12 && xi.y.abs() < 1e-12 && xi.yaw.abs() < 1e-12);
    }
}

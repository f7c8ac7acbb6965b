//! Unicycle kinematics with exact integration over one step.

/// A robot's pose in the world frame.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Pose {
    /// Metres.
    pub x: f64,
    /// Metres.
    pub y: f64,
    /// Heading, radians in (-pi, pi].
    pub theta: f64,
}

impl From<[f32; 3]> for Pose {
    /// A pose as the wire carries it, (x, y, theta) in `f32`, widened exactly.
    fn from([x, y, theta]: [f32; 3]) -> Self {
        Self {
            x: f64::from(x),
            y: f64::from(y),
            theta: f64::from(theta),
        }
    }
}

/// sin(h) / h, continuous at 0.
fn sinc(h: f64) -> f64 {
    if h.abs() < 1e-6 { 1.0 - h * h / 6.0 } else { h.sin() / h }
}

/// Wraps an angle to (-pi, pi].
pub fn wrap_angle(angle: f64) -> f64 {
    let wrapped = angle.rem_euclid(std::f64::consts::TAU);
    if wrapped > std::f64::consts::PI {
        wrapped - std::f64::consts::TAU
    } else {
        wrapped
    }
}

/// Integrates x' = v cos(theta), y' = v sin(theta), theta' = w exactly over `dt` with constant
/// (v, w): the robot moves along a circular arc whose chord is v dt sinc(w dt / 2) at the mean
/// heading.
pub fn integrate(pose: Pose, v: f64, w: f64, dt: f64) -> Pose {
    debug_assert!(dt > 0.0 && v.is_finite() && w.is_finite());
    let half_turn = 0.5 * w * dt;
    let chord = v * dt * sinc(half_turn);
    let mean_heading = pose.theta + half_turn;
    Pose {
        x: pose.x + chord * mean_heading.cos(),
        y: pose.y + chord * mean_heading.sin(),
        theta: wrap_angle(pose.theta + w * dt),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn straight_line_and_spin_in_place() {
        let p = integrate(
            Pose {
                x: 1.0,
                y: 2.0,
                theta: 0.0,
            },
            0.5,
            0.0,
            0.1,
        );
        assert!((p.x - 1.05).abs() < 1e-12 && (p.y - 2.0).abs() < 1e-12);
        let q = integrate(Pose::default(), 0.0, 1.0, 0.1);
        assert!(q.x.abs() < 1e-12 && q.y.abs() < 1e-12 && (q.theta - 0.1).abs() < 1e-12);
    }

    #[test]
    fn matches_closed_form_arc() {
        // Closed form: x(t) = x0 + v/w (sin(th0 + w t) - sin th0), y(t) = y0 - v/w (cos(th0 + w t) - cos th0).
        let (v, w, th0) = (0.4, -0.8, 0.7);
        let mut pose = Pose {
            x: 3.0,
            y: -1.0,
            theta: th0,
        };
        for step in 1..=50 {
            pose = integrate(pose, v, w, 0.1);
            let t = step as f64 * 0.1;
            let x = 3.0 + v / w * ((th0 + w * t).sin() - th0.sin());
            let y = -1.0 - v / w * ((th0 + w * t).cos() - th0.cos());
            assert!((pose.x - x).abs() < 1e-9, "x at step {step}");
            assert!((pose.y - y).abs() < 1e-9, "y at step {step}");
            assert!((wrap_angle(pose.theta - (th0 + w * t))).abs() < 1e-9);
        }
    }

    #[test]
    fn wrap_angle_range() {
        for a in [-10.0, -std::f64::consts::PI, 0.0, 3.5, 7.0] {
            let w = wrap_angle(a);
            assert!(w > -std::f64::consts::PI - 1e-12 && w <= std::f64::consts::PI);
            assert!(
                ((w - a) / std::f64::consts::TAU).fract().abs() < 1e-9
                    || ((w - a) / std::f64::consts::TAU).fract().abs() > 1.0 - 1e-9
            );
        }
    }
}

//! Helpers for translators of differential-drive motor controllers: body
//! twist to wheel speeds, control strings to wheel speeds, and dead
//! reckoning from wheel travel (what a controller that reports encoder
//! counts needs turned into a pose).

use crate::Params;

/// A differential-drive base.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Geometry {
    /// Distance between the wheels, metres.
    pub wheel_base: f64,
    /// Fastest wheel surface speed, m/s: commands are scaled down to fit.
    pub max_wheel_speed: f64,
}

impl Geometry {
    /// `wheel-base` and `max-wheel-speed` from the link's parameters, with
    /// these defaults when absent.
    pub fn from_params(params: &Params, wheel_base: f64, max_wheel_speed: f64) -> Result<Geometry, String> {
        let number = |name: &str, default: f64| params.text(name).map_or(Ok(default), |_| params.number(name));
        let geometry = Geometry {
            wheel_base: number("wheel-base", wheel_base)?,
            max_wheel_speed: number("max-wheel-speed", max_wheel_speed)?,
        };
        if !(geometry.wheel_base > 0.0 && geometry.max_wheel_speed > 0.0) {
            return Err("wheel-base and max-wheel-speed must be positive".into());
        }
        Ok(geometry)
    }

    /// Wheel speeds (left, right) in m/s for a body twist, scaled down
    /// together (keeping the curvature) when a wheel would be too fast.
    pub fn wheels(&self, linear: f64, angular: f64) -> (f64, f64) {
        let half = angular * self.wheel_base / 2.0;
        let (left, right) = (linear - half, linear + half);
        let fastest = left.abs().max(right.abs());
        if fastest > self.max_wheel_speed {
            let scale = self.max_wheel_speed / fastest;
            (left * scale, right * scale)
        } else {
            (left, right)
        }
    }

    /// Wheel speeds (left, right) in m/s for a control string: `STOP` is
    /// (0, 0), `VEL v w` a twist; anything else (`GOTO`) is refused.
    pub fn command(&self, command: &str) -> Result<(f64, f64), String> {
        let words: Vec<&str> = command.split_ascii_whitespace().collect();
        match words.as_slice() {
            [stop] if stop.eq_ignore_ascii_case("STOP") => Ok((0.0, 0.0)),
            [vel, linear, angular] if vel.eq_ignore_ascii_case("VEL") => {
                let linear: f64 = linear.parse().map_err(|_| format!("bad linear speed '{linear}'"))?;
                let angular: f64 = angular.parse().map_err(|_| format!("bad angular speed '{angular}'"))?;
                if !linear.is_finite() || !angular.is_finite() {
                    return Err("speeds must be finite".into());
                }
                Ok(self.wheels(linear, angular))
            }
            _ => Err(format!("the motors take STOP and VEL, not '{command}'")),
        }
    }
}

/// Dead reckoning of a differential-drive base from its wheels' travel.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Odometry {
    wheel_base: f64,
    /// Pose: metres, metres, radians in (-pi, pi].
    pub x: f64,
    pub y: f64,
    pub heading: f64,
}

impl Odometry {
    /// Starts at `(x, y, heading)`.
    pub fn new(wheel_base: f64, x: f64, y: f64, heading: f64) -> Odometry {
        Odometry { wheel_base, x, y, heading: wrap(heading) }
    }

    /// `origin-x`, `origin-y` and `origin-heading` (metres, radians) from
    /// the link's parameters; 0 when absent.
    pub fn from_params(params: &Params, wheel_base: f64) -> Result<Odometry, String> {
        let number = |name: &str| {
            let value = params.text(name).map_or(Ok(0.0), |_| params.number(name))?;
            if value.is_finite() { Ok(value) } else { Err(format!("parameter '{name}' must be finite")) }
        };
        Ok(Odometry::new(wheel_base, number("origin-x")?, number("origin-y")?, number("origin-heading")?))
    }

    /// Moves by the wheels' travel since the last call (metres, forward
    /// positive), along an arc approximated at its mid heading. A step that
    /// would leave the pose not finite (a controller reporting absurd
    /// positions, which would poison every later pose) is refused: the pose
    /// stays where it was and the answer is `false`.
    pub fn advance(&mut self, left: f64, right: f64) -> bool {
        let distance = (left + right) / 2.0;
        let turn = (right - left) / self.wheel_base;
        let mid = self.heading + turn / 2.0;
        let (x, y) = (self.x + distance * mid.cos(), self.y + distance * mid.sin());
        let heading = wrap(self.heading + turn);
        if !(x.is_finite() && y.is_finite() && heading.is_finite()) {
            return false;
        }
        (self.x, self.y, self.heading) = (x, y, heading);
        true
    }

    pub fn pose(&self) -> crate::Pose {
        crate::Pose { x: self.x, y: self.y, heading: self.heading }
    }
}

/// An angle in (-pi, pi].
pub fn wrap(angle: f64) -> f64 {
    use std::f64::consts::{PI, TAU};
    let a = angle.rem_euclid(TAU);
    if a > PI { a - TAU } else { a }
}

//! The simulated robot's body and world physics: a round differential-drive
//! robot, exact arc integration in small steps, range rays, collisions.
//! Pure and time-free: the caller says how much time passes.

use serde::Serialize;

use super::SimError;
use super::world::{Obstacle, Point, World};
use crate::robot::translator::DriveGeometry;

/// Longest physics step; longer intervals are split. At 1 m/s a step moves
/// 5 mm, far less than any robot radius, so nothing is tunnelled through.
pub const MAX_STEP_S: f64 = 0.005;

/// Contacts kept with their time and place (the count goes on): a robot
/// pushing into a wall for an hour must not grow the status.
pub const MAX_CONTACTS_KEPT: usize = 16;

/// Where and when the robot ran into something.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, schemars::JsonSchema)]
pub struct Contact {
    /// Simulated seconds since start.
    pub time_s: f64,
    /// Where the robot's centre was (m).
    pub x: f64,
    pub y: f64,
}

/// The robot's body and sensors.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Body {
    /// The robot is a disc of this radius, metres.
    pub radius: f64,
    pub geometry: DriveGeometry,
    /// Number of range rays, spread evenly over `fov` (right to left).
    pub rays: usize,
    /// Angle covered by the rays, radians.
    pub fov: f64,
    /// Longest range reading, metres.
    pub max_range: f64,
}

/// What the report and the live view show of the simulation.
#[derive(Clone, Debug, PartialEq, Serialize, schemars::JsonSchema)]
pub struct SimStatus {
    pub x: f64,
    pub y: f64,
    pub heading: f64,
    /// Simulated seconds since start.
    pub time_s: f64,
    pub goal: [f64; 2],
    pub goal_reached: bool,
    pub goal_reached_at_s: Option<f64>,
    pub distance_travelled_m: f64,
    /// Times the robot ran into something (each contact counts once).
    pub collisions: u64,
    /// The first [`MAX_CONTACTS_KEPT`] of them.
    pub contacts: Vec<Contact>,
    pub bumper: bool,
    pub ranges: Vec<f64>,
}

/// The world and the robot in it.
#[derive(Clone, Debug)]
pub struct Simulation {
    world: World,
    body: Body,
    x: f64,
    y: f64,
    heading: f64,
    left: f64,
    right: f64,
    time_s: f64,
    distance: f64,
    collisions: u64,
    contacts: Vec<Contact>,
    bumper: bool,
    goal_reached_at: Option<f64>,
}

impl Simulation {
    /// The robot at the world's start pose. Fails if it starts inside
    /// something.
    pub fn new(world: World, body: Body) -> Result<Simulation, SimError> {
        let (start, heading) = world.start;
        let sim = Simulation {
            x: start.x,
            y: start.y,
            heading,
            world,
            body,
            left: 0.0,
            right: 0.0,
            time_s: 0.0,
            distance: 0.0,
            collisions: 0,
            contacts: Vec::new(),
            bumper: false,
            goal_reached_at: None,
        };
        if let Some(why) = sim.blocked(start.x, start.y) {
            return Err(SimError::StartBlocked { x: start.x, y: start.y, why });
        }
        Ok(sim)
    }

    /// The robot back at the world's start pose, at rest, with time, distance,
    /// collisions and the goal forgotten.
    pub fn reset(&mut self) {
        let (start, heading) = self.world.start;
        *self = Simulation {
            x: start.x,
            y: start.y,
            heading,
            world: self.world.clone(),
            body: self.body,
            left: 0.0,
            right: 0.0,
            time_s: 0.0,
            distance: 0.0,
            collisions: 0,
            contacts: Vec::new(),
            bumper: false,
            goal_reached_at: None,
        };
    }

    /// Puts the robot at (`x`, `y`) facing `heading` (rad), at rest. Refused
    /// (nothing changes) where the body would overlap an obstacle, or for a
    /// coordinate that is not finite.
    pub fn set_pose(&mut self, x: f64, y: f64, heading: f64) -> Result<(), SimError> {
        if !(x.is_finite() && y.is_finite() && heading.is_finite()) {
            return Err(SimError::BadPose(format!("({x}, {y}, {heading}) is not a finite pose")));
        }
        if let Some(why) = self.blocked(x, y) {
            return Err(SimError::BadPose(format!("({x}, {y}) {why}")));
        }
        self.x = x;
        self.y = y;
        self.heading = wrap(heading);
        self.left = 0.0;
        self.right = 0.0;
        self.bumper = false;
        Ok(())
    }

    /// Simulated seconds since the start (or the last reset).
    pub fn time_s(&self) -> f64 {
        self.time_s
    }

    /// Sets the wheel speeds (m/s), limited to the body's fastest.
    pub fn set_wheels(&mut self, left: f64, right: f64) {
        let max = self.body.geometry.max_wheel_speed;
        let clean = |v: f64| if v.is_finite() { v.clamp(-max, max) } else { 0.0 };
        self.left = clean(left);
        self.right = clean(right);
    }

    /// Advances the world by `dt` seconds.
    pub fn step(&mut self, dt: f64) {
        if !(dt > 0.0 && dt.is_finite()) {
            return;
        }
        let steps = (dt / MAX_STEP_S).ceil().max(1.0) as usize;
        let h = dt / steps as f64;
        let (v, w) = self.body.geometry.twist(self.left, self.right);
        for _ in 0..steps {
            self.time_s += h;
            let (x, y, heading) = if w.abs() < 1e-9 {
                (self.x + v * self.heading.cos() * h, self.y + v * self.heading.sin() * h, self.heading)
            } else {
                let next = self.heading + w * h;
                let r = v / w;
                (self.x + r * (next.sin() - self.heading.sin()), self.y - r * (next.cos() - self.heading.cos()), next)
            };
            if self.collides(x, y) {
                // Blocked: the wheels slip, the body may still turn in place.
                if !self.bumper {
                    self.collisions += 1;
                    if self.contacts.len() < MAX_CONTACTS_KEPT {
                        self.contacts.push(Contact { time_s: self.time_s, x: self.x, y: self.y });
                    }
                    self.bumper = true;
                }
                self.heading = wrap(heading);
            } else {
                self.distance += (x - self.x).hypot(y - self.y);
                self.x = x;
                self.y = y;
                self.heading = wrap(heading);
                self.bumper = false;
            }
            let (goal, radius) = self.world.goal;
            if self.goal_reached_at.is_none() && (self.x - goal.x).hypot(self.y - goal.y) <= radius {
                self.goal_reached_at = Some(self.time_s);
            }
        }
    }

    /// Why the robot cannot be put at (`x`, `y`): its body would touch an
    /// obstacle, or it would be inside a box or outside the bounds (where
    /// no side is near, but it could never get out).
    fn blocked(&self, x: f64, y: f64) -> Option<String> {
        let inside = |(a, b): (Point, Point)| a.x < x && x < b.x && a.y < y && y < b.y;
        let corners = |(a, b): (Point, Point)| format!("{} {} {} {}", a.x, a.y, b.x, b.y);
        if !inside(self.world.bounds) {
            Some(format!("is outside the world's bounds {}", corners(self.world.bounds)))
        } else if let Some(solid) = self.world.boxes.iter().find(|b| inside(**b)) {
            Some(format!("is inside the box {}", corners(*solid)))
        } else if self.collides(x, y) {
            Some(format!("is within {} m of an obstacle", self.body.radius))
        } else {
            None
        }
    }

    fn collides(&self, x: f64, y: f64) -> bool {
        let p = Point { x, y };
        self.world.obstacles.iter().any(|o| match *o {
            Obstacle::Segment(a, b) => distance_to_segment(p, a, b) < self.body.radius,
            Obstacle::Circle(c, r) => (p.x - c.x).hypot(p.y - c.y) < self.body.radius + r,
        })
    }

    /// Range readings from the robot's centre, rays from -fov/2 (right) to
    /// +fov/2 (left) of the heading.
    pub fn ranges(&self) -> Vec<f64> {
        let n = self.body.rays.max(1);
        let (first, step) = if n > 1 { (-self.body.fov / 2.0, self.body.fov / (n - 1) as f64) } else { (0.0, 0.0) };
        (0..n).map(|i| self.cast(self.heading + first + step * i as f64)).collect()
    }

    fn cast(&self, angle: f64) -> f64 {
        let origin = Point { x: self.x, y: self.y };
        let d = Point { x: angle.cos(), y: angle.sin() };
        self.world
            .obstacles
            .iter()
            .filter_map(|o| match *o {
                Obstacle::Segment(a, b) => ray_segment(origin, d, a, b),
                Obstacle::Circle(c, r) => ray_circle(origin, d, c, r),
            })
            .fold(self.body.max_range, f64::min)
    }

    pub fn pose(&self) -> (f64, f64, f64) {
        (self.x, self.y, self.heading)
    }

    pub fn bumper(&self) -> bool {
        self.bumper
    }

    pub fn status(&self) -> SimStatus {
        SimStatus {
            x: self.x,
            y: self.y,
            heading: self.heading,
            time_s: self.time_s,
            goal: [self.world.goal.0.x, self.world.goal.0.y],
            goal_reached: self.goal_reached_at.is_some(),
            goal_reached_at_s: self.goal_reached_at,
            distance_travelled_m: self.distance,
            collisions: self.collisions,
            contacts: self.contacts.clone(),
            bumper: self.bumper,
            ranges: self.ranges(),
        }
    }
}

fn wrap(angle: f64) -> f64 {
    let a = angle.rem_euclid(std::f64::consts::TAU);
    if a > std::f64::consts::PI { a - std::f64::consts::TAU } else { a }
}

fn cross(a: Point, b: Point) -> f64 {
    a.x * b.y - a.y * b.x
}

fn distance_to_segment(p: Point, a: Point, b: Point) -> f64 {
    let (ex, ey) = (b.x - a.x, b.y - a.y);
    let length2 = ex * ex + ey * ey;
    let t = if length2 > 0.0 { (((p.x - a.x) * ex + (p.y - a.y) * ey) / length2).clamp(0.0, 1.0) } else { 0.0 };
    (p.x - (a.x + t * ex)).hypot(p.y - (a.y + t * ey))
}

fn ray_segment(origin: Point, d: Point, a: Point, b: Point) -> Option<f64> {
    let e = Point { x: b.x - a.x, y: b.y - a.y };
    let denom = cross(d, e);
    if denom.abs() < 1e-12 {
        return None;
    }
    let ao = Point { x: a.x - origin.x, y: a.y - origin.y };
    let t = cross(ao, e) / denom;
    let s = cross(ao, d) / denom;
    (t >= 0.0 && (0.0..=1.0).contains(&s)).then_some(t)
}

fn ray_circle(origin: Point, d: Point, c: Point, r: f64) -> Option<f64> {
    let f = Point { x: origin.x - c.x, y: origin.y - c.y };
    let b = f.x * d.x + f.y * d.y;
    let disc = b * b - (f.x * f.x + f.y * f.y - r * r);
    if disc < 0.0 {
        return None;
    }
    let root = disc.sqrt();
    [-b - root, -b + root].into_iter().find(|t| *t >= 0.0)
}

#[cfg(test)]
mod tests {
    use std::path::Path;

    use super::*;
    use crate::sim::world;

    const BODY: Body = Body {
        radius: 0.2,
        geometry: DriveGeometry { wheel_base: 0.3, max_wheel_speed: 0.5 },
        rays: 3,
        fov: std::f64::consts::PI,
        max_range: 4.0,
    };

    fn sim(text: &str) -> Simulation {
        let world = world::parse(Path::new("t.world"), text).map_err(|e| e.to_string());
        match world.and_then(|w| Simulation::new(w, BODY).map_err(|e| e.to_string())) {
            Ok(sim) => sim,
            Err(e) => panic!("{e}"),
        }
    }

    #[test]
    fn straight_driving_and_turning_follow_the_kinematics() {
        let mut s = sim("bounds 0 0 10 10\nstart 1 1 0\ngoal 9 9 0.2\n");
        s.set_wheels(0.2, 0.2);
        s.step(1.0);
        let (x, y, h) = s.pose();
        assert!((x - 1.2).abs() < 1e-9 && (y - 1.0).abs() < 1e-9 && h.abs() < 1e-9);
        // Spin in place at 1 rad/s for pi/2 s: a quarter turn, no travel.
        s.set_wheels(-0.15, 0.15);
        s.step(std::f64::consts::FRAC_PI_2);
        let (x2, _, h2) = s.pose();
        assert!((h2 - std::f64::consts::FRAC_PI_2).abs() < 1e-9 && (x2 - 1.2).abs() < 1e-9);
        assert!((s.status().distance_travelled_m - 0.2).abs() < 1e-9);
    }

    #[test]
    fn rays_see_the_nearest_obstacle_and_cap_at_max_range() {
        // Facing +x from (1, 5): a wall at x = 3, a circle to the left.
        let s = sim("bounds 0 0 20 10\nstart 1 5 0\ngoal 9 9 0.2\nwall 3 0 3 6\ncircle 1 7 0.5\n");
        let r = s.ranges();
        // Right ray (-y): bounds at y = 0, 5 m away, capped at 4. Ahead: 2 m.
        // Left (+y): the circle's edge at y = 6.5.
        assert!((r[0] - 4.0).abs() < 1e-9 && (r[1] - 2.0).abs() < 1e-9 && (r[2] - 1.5).abs() < 1e-9, "{r:?}");
    }

    #[test]
    fn a_collision_blocks_the_robot_and_counts_once() {
        let mut s = sim("bounds 0 0 10 10\nstart 1 5 0\ngoal 9 9 0.2\nwall 2 0 2 10\n");
        s.set_wheels(0.5, 0.5);
        s.step(5.0);
        let status = s.status();
        assert_eq!(status.collisions, 1);
        assert!(status.bumper);
        // Stopped within a step of the wall: centre at 2 - radius.
        assert!(status.x < 1.8 && status.x > 1.79, "{}", status.x);
        s.set_wheels(-0.5, -0.5);
        s.step(0.5);
        assert!(!s.bumper());
    }

    #[test]
    fn the_goal_is_reached_when_the_centre_enters_it() {
        let mut s = sim("bounds 0 0 10 10\nstart 1 1 0\ngoal 2 1 0.1\n");
        s.set_wheels(0.5, 0.5);
        s.step(1.0);
        assert!(!s.status().goal_reached);
        s.step(1.0);
        let at = s.status().goal_reached_at_s.unwrap_or_default();
        assert!((at - 1.8).abs() < 0.01, "{at}");
    }

    #[test]
    fn reset_and_set_pose_restart_an_experiment() {
        let mut s = sim("bounds 0 0 10 10\nstart 1 5 0\ngoal 9 9 0.2\nwall 2 0 2 10\n");
        s.set_wheels(0.5, 0.5);
        s.step(5.0);
        assert_eq!(s.status().collisions, 1);
        s.reset();
        let fresh = sim("bounds 0 0 10 10\nstart 1 5 0\ngoal 9 9 0.2\nwall 2 0 2 10\n");
        assert_eq!(s.status(), fresh.status());
        // At rest after a reset: time passes, nothing moves.
        s.step(1.0);
        assert_eq!(s.pose(), fresh.pose());
        assert!(s.set_pose(1.9, 5.0, 0.0).is_err(), "inside the wall");
        assert!(s.set_pose(f64::NAN, 5.0, 0.0).is_err());
        assert_eq!(s.pose(), fresh.pose(), "a refused pose changes nothing");
        assert!(s.set_pose(0.5, 2.0, 7.0).is_ok());
        let (x, y, h) = s.pose();
        assert!(x == 0.5 && y == 2.0 && (h - (7.0 - std::f64::consts::TAU)).abs() < 1e-12);
    }

    #[test]
    fn starting_inside_an_obstacle_is_refused() {
        let world = world::parse(Path::new("t.world"), "bounds 0 0 10 10\nstart 1 1 0\ngoal 9 9 0.2\ncircle 1 1 0.5\n");
        assert!(
            world.map_err(|e| e.to_string()).and_then(|w| Simulation::new(w, BODY).map_err(|e| e.to_string())).is_err()
        );
    }

    #[test]
    fn a_pose_is_refused_where_the_robot_could_never_drive_with_the_reason() {
        let text = "bounds 0 0 10 8\nstart 1 1 0\ngoal 9 7 0.2\nbox 4 3 6 5\ncircle 8 2 0.5\n";
        let cases: [(f64, f64, Option<&str>); 7] = [
            (5.0, 4.0, Some("(5, 4) is inside the box 4 3 6 5")),
            (4.5, 3.5, Some("(4.5, 3.5) is inside the box 4 3 6 5")),
            (3.9, 4.0, Some("(3.9, 4) is within 0.2 m of an obstacle")),
            (8.0, 2.0, Some("(8, 2) is within 0.2 m of an obstacle")),
            (12.0, 4.0, Some("(12, 4) is outside the world's bounds 0 0 10 8")),
            (-3.0, -3.0, Some("(-3, -3) is outside the world's bounds 0 0 10 8")),
            (3.0, 4.0, None),
        ];
        for (x, y, refused) in cases {
            let mut s = sim(text);
            let before = s.pose();
            match (s.set_pose(x, y, 0.0), refused) {
                (Ok(()), None) => assert_eq!(s.pose(), (x, y, 0.0)),
                (Err(e), Some(why)) => {
                    assert_eq!(e.to_string(), why);
                    assert_eq!(s.pose(), before, "a refused pose changes nothing");
                }
                (got, want) => panic!("({x}, {y}): got {got:?}, want {want:?}"),
            }
        }
        let inside = world::parse(Path::new("t.world"), "bounds 0 0 10 8\nstart 5 4 0\ngoal 9 7 0.2\nbox 4 3 6 5\n");
        let refused = inside
            .map_err(|e| e.to_string())
            .and_then(|w| Simulation::new(w, BODY).map(drop).map_err(|e| e.to_string()));
        assert_eq!(refused, Err("the start (5, 4) is inside the box 4 3 6 5".to_string()));
    }
}

//! The simulator's camera picture: the simulated world seen from above
//! (bounds and walls, round obstacles, the goal, the range rays, the robot
//! with its heading), drawn into an RGB buffer. Pure: a [`Scene`] in, pixels
//! out, so tests check where things are drawn without a clock or a thread.

use crate::sim::physics::Body;
use crate::sim::world::{Obstacle, World};

/// Colours (RGB).
pub const BACKGROUND: [u8; 3] = [245, 245, 240];
pub const WALL: [u8; 3] = [40, 40, 40];
pub const GOAL: [u8; 3] = [40, 170, 60];
pub const RAY: [u8; 3] = [230, 160, 40];
pub const ROBOT: [u8; 3] = [30, 90, 220];
pub const HEADING: [u8; 3] = [250, 250, 250];

/// Blank pixels around the world's bounds.
const MARGIN_PX: f64 = 4.0;

/// What one frame shows: the world (fixed), the robot's body and where it
/// is, and its range readings (rays right to left over the body's `fov`).
#[derive(Clone, Debug)]
pub struct Scene<'a> {
    pub world: &'a World,
    pub body: Body,
    pub pose: (f64, f64, f64),
    pub ranges: &'a [f64],
}

/// World metres to pixels: the bounds fitted into the picture, keeping
/// their aspect, x to the right, y up (the picture's rows go down).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Viewport {
    /// Pixels per metre.
    pub scale: f64,
    x0: f64,
    y0: f64,
    offset_x: f64,
    offset_y: f64,
    height: f64,
}

impl Viewport {
    /// The viewport showing `world`'s bounds in a `width` x `height` picture.
    pub fn fit(world: &World, width: u32, height: u32) -> Viewport {
        let (lo, hi) = world.bounds;
        let (span_x, span_y) = ((hi.x - lo.x).max(1e-9), (hi.y - lo.y).max(1e-9));
        let (w, h) = (f64::from(width), f64::from(height));
        let scale = ((w - 2.0 * MARGIN_PX).max(1.0) / span_x).min((h - 2.0 * MARGIN_PX).max(1.0) / span_y);
        Viewport {
            scale,
            x0: lo.x,
            y0: lo.y,
            offset_x: (w - span_x * scale) / 2.0,
            offset_y: (h - span_y * scale) / 2.0,
            height: h,
        }
    }

    /// The pixel (column, row; fractional) showing world point (`x`, `y`).
    pub fn to_pixel(&self, x: f64, y: f64) -> (f64, f64) {
        (self.offset_x + (x - self.x0) * self.scale, self.height - (self.offset_y + (y - self.y0) * self.scale))
    }
}

/// An RGB picture, row by row from the top.
#[derive(Clone, Debug, PartialEq)]
pub struct Picture {
    pub width: u32,
    pub height: u32,
    pub rgb: Vec<u8>,
}

impl Picture {
    fn new(width: u32, height: u32) -> Picture {
        let mut rgb = Vec::with_capacity(width as usize * height as usize * 3);
        for _ in 0..(width as usize * height as usize) {
            rgb.extend_from_slice(&BACKGROUND);
        }
        Picture { width, height, rgb }
    }

    /// The colour at column `x`, row `y`, if inside.
    pub fn pixel(&self, x: u32, y: u32) -> Option<[u8; 3]> {
        if x >= self.width || y >= self.height {
            return None;
        }
        let at = (y as usize * self.width as usize + x as usize) * 3;
        self.rgb.get(at..at + 3).map(|p| [p[0], p[1], p[2]])
    }

    fn put(&mut self, x: i64, y: i64, colour: [u8; 3]) {
        if x < 0 || y < 0 || x >= i64::from(self.width) || y >= i64::from(self.height) {
            return;
        }
        let at = (y as usize * self.width as usize + x as usize) * 3;
        if let Some(p) = self.rgb.get_mut(at..at + 3) {
            p.copy_from_slice(&colour);
        }
    }

    /// A line from `a` to `b` (pixels), `thick` pixels wide.
    fn line(&mut self, a: (f64, f64), b: (f64, f64), thick: i64, colour: [u8; 3]) {
        let steps = (b.0 - a.0).abs().max((b.1 - a.1).abs()).ceil().clamp(1.0, MAX_LINE_STEPS) as usize;
        for i in 0..=steps {
            let t = i as f64 / steps as f64;
            let (x, y) = ((a.0 + (b.0 - a.0) * t).round() as i64, (a.1 + (b.1 - a.1) * t).round() as i64);
            for dy in 0..thick {
                for dx in 0..thick {
                    self.put(x + dx - thick / 2, y + dy - thick / 2, colour);
                }
            }
        }
    }

    /// A filled disc centred at `c` (pixels) of radius `r` pixels (at
    /// least one pixel is drawn).
    fn disc(&mut self, c: (f64, f64), r: f64, colour: [u8; 3]) {
        let r = r.max(0.5);
        let (x0, x1) = ((c.0 - r).floor() as i64, (c.0 + r).ceil() as i64);
        let (y0, y1) = ((c.1 - r).floor() as i64, (c.1 + r).ceil() as i64);
        for y in y0.max(0)..=y1.min(i64::from(self.height)) {
            for x in x0.max(0)..=x1.min(i64::from(self.width)) {
                let (dx, dy) = (x as f64 + 0.5 - c.0, y as f64 + 0.5 - c.1);
                if dx * dx + dy * dy <= r * r || (x == c.0.floor() as i64 && y == c.1.floor() as i64) {
                    self.put(x, y, colour);
                }
            }
        }
    }

    /// A circle's outline.
    fn ring(&mut self, c: (f64, f64), r: f64, colour: [u8; 3]) {
        let steps = (r * 8.0).ceil().clamp(8.0, MAX_LINE_STEPS) as usize;
        let point = |i: usize| {
            let a = std::f64::consts::TAU * i as f64 / steps as f64;
            (c.0 + r * a.cos(), c.1 + r * a.sin())
        };
        for i in 0..steps {
            self.line(point(i), point(i + 1), 2, colour);
        }
    }
}

/// Most pixels one line or outline is drawn with: a wall from far outside
/// the picture must not cost a frame millions of steps.
const MAX_LINE_STEPS: f64 = 8192.0;

/// Draws `scene` into a `width` x `height` picture.
pub fn render(scene: &Scene<'_>, width: u32, height: u32) -> Picture {
    let mut picture = Picture::new(width, height);
    let view = Viewport::fit(scene.world, width, height);
    let (gx, gy) = (scene.world.goal.0.x, scene.world.goal.0.y);
    picture.ring(view.to_pixel(gx, gy), scene.world.goal.1 * view.scale, GOAL);
    let (x, y, heading) = scene.pose;
    let robot = view.to_pixel(x, y);
    let n = scene.ranges.len();
    let (first, step) = if n > 1 { (-scene.body.fov / 2.0, scene.body.fov / (n - 1) as f64) } else { (0.0, 0.0) };
    for (i, range) in scene.ranges.iter().enumerate() {
        let angle = heading + first + step * i as f64;
        let reach = if range.is_finite() { range.clamp(0.0, scene.body.max_range) } else { scene.body.max_range };
        picture.line(robot, view.to_pixel(x + reach * angle.cos(), y + reach * angle.sin()), 1, RAY);
    }
    for obstacle in &scene.world.obstacles {
        match *obstacle {
            Obstacle::Segment(a, b) => picture.line(view.to_pixel(a.x, a.y), view.to_pixel(b.x, b.y), 2, WALL),
            Obstacle::Circle(c, r) => picture.disc(view.to_pixel(c.x, c.y), r * view.scale, WALL),
        }
    }
    let radius_px = scene.body.radius * view.scale;
    picture.disc(robot, radius_px, ROBOT);
    let nose = view.to_pixel(x + scene.body.radius * heading.cos(), y + scene.body.radius * heading.sin());
    picture.line(robot, nose, 2, HEADING);
    picture
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]

    use std::path::Path;

    use super::*;
    use crate::robot::translator::DriveGeometry;
    use crate::sim::world;

    fn world() -> World {
        world::parse(Path::new("t.world"), "bounds 0 0 10 5\nstart 1 1 0\ngoal 9 4 0.3\ncircle 5 2.5 0.5\n").unwrap()
    }

    fn body() -> Body {
        Body {
            radius: 0.25,
            geometry: DriveGeometry { wheel_base: 0.3, max_wheel_speed: 0.5 },
            rays: 3,
            fov: std::f64::consts::PI,
            max_range: 2.0,
        }
    }

    #[test]
    fn the_viewport_fits_the_bounds_keeping_their_aspect() {
        let view = Viewport::fit(&world(), 208, 208);
        // 10 m wide in 200 px: 20 px/m; 5 m tall centred in 208 rows.
        assert_eq!(view.scale, 20.0);
        assert_eq!(view.to_pixel(0.0, 0.0), (4.0, 154.0));
        assert_eq!(view.to_pixel(10.0, 5.0), (204.0, 54.0));
    }

    #[test]
    fn the_robot_is_drawn_where_the_pose_says() {
        let world = world();
        // (pose, picture size)
        let cases = [((1.0, 1.0, 0.0), (208, 208)), ((8.0, 4.0, 1.5), (208, 208)), ((3.0, 2.0, -2.0), (320, 240))];
        for ((x, y, heading), (w, h)) in cases {
            let scene = Scene { world: &world, body: body(), pose: (x, y, heading), ranges: &[1.0, 1.0, 1.0] };
            let picture = render(&scene, w, h);
            let view = Viewport::fit(&world, w, h);
            let (px, py) = view.to_pixel(x, y);
            // Behind the centre (the heading line is in front of it).
            let behind = view.to_pixel(x - 0.15 * heading.cos(), y - 0.15 * heading.sin());
            assert_eq!(picture.pixel(behind.0 as u32, behind.1 as u32), Some(ROBOT), "pose {x},{y} in {w}x{h}");
            let nose = view.to_pixel(x + 0.2 * heading.cos(), y + 0.2 * heading.sin());
            assert_eq!(picture.pixel(nose.0 as u32, nose.1 as u32), Some(HEADING), "heading {heading}");
            // Nothing of the robot outside its disc (one radius and 3 px off).
            let off = view.scale * 0.25 + 3.0;
            assert_ne!(picture.pixel((px + off) as u32, py as u32), Some(ROBOT));
            assert_ne!(picture.pixel(px as u32, (py - off) as u32), Some(ROBOT));
        }
    }

    #[test]
    fn walls_obstacles_goal_and_rays_are_drawn() {
        let world = world();
        let scene = Scene { world: &world, body: body(), pose: (1.0, 1.0, 0.0), ranges: &[1.0, 1.5, 0.5] };
        let picture = render(&scene, 208, 208);
        let view = Viewport::fit(&world, 208, 208);
        let at = |x: f64, y: f64| {
            let (px, py) = view.to_pixel(x, y);
            picture.pixel(px as u32, py as u32)
        };
        assert_eq!(at(5.0, 0.0), Some(WALL), "the bottom bound");
        assert_eq!(at(5.0, 2.5), Some(WALL), "the circle");
        assert_eq!(at(9.3, 4.0), Some(GOAL), "the goal's ring");
        // The middle ray (straight ahead, 1.5 m); the left ray is 0.5 m long.
        assert_eq!(at(2.2, 1.0), Some(RAY));
        assert_eq!(at(1.0, 1.4), Some(RAY));
        assert_eq!(at(1.0, 1.7), Some(BACKGROUND));
    }
}

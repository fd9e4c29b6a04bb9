//! World files (`config/worlds/*.world`): the simulated robot's 2D world.
//! One statement per line, `#` starts a comment, lengths in metres, angles
//! in radians:
//!
//! ```text
//! bounds X0 Y0 X1 Y1        # the arena; walls all around (required, once)
//! start X Y HEADING         # where the robot starts (required, once)
//! goal X Y RADIUS           # where it should go (required, once)
//! wall X1 Y1 X2 Y2          # a wall segment
//! box X0 Y0 X1 Y1           # an axis-aligned rectangular obstacle
//! circle X Y RADIUS         # a round obstacle
//! ```
//!
//! Errors are reported like robot-file errors: `path:line:column: message`,
//! all of them.

use std::path::Path;

use crate::config::{Diagnostic, Diagnostics, SourceMap};

/// Largest world file read.
pub const MAX_WORLD_BYTES: u64 = 1 << 20;
/// Most obstacles in a world: each costs every range ray a test per step.
pub const MAX_OBSTACLES: usize = 10_000;

#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, schemars::JsonSchema)]
pub struct Point {
    pub x: f64,
    pub y: f64,
}

/// Something the robot cannot pass through.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, schemars::JsonSchema)]
#[serde(rename_all = "lowercase")]
pub enum Obstacle {
    Segment(Point, Point),
    Circle(Point, f64),
}

#[derive(Clone, Debug, PartialEq, serde::Serialize, schemars::JsonSchema)]
pub struct World {
    pub bounds: (Point, Point),
    pub start: (Point, f64),
    pub goal: (Point, f64),
    /// Walls, box sides, circles and the four sides of the bounds.
    pub obstacles: Vec<Obstacle>,
    /// The boxes' corners (lower left, upper right): their sides are in
    /// `obstacles`, and this says where their solid insides are.
    #[serde(skip)]
    pub boxes: Vec<(Point, Point)>,
}

/// Reads and parses the world file at `path`.
pub fn load(path: &Path) -> Result<World, Diagnostics> {
    let fail =
        |message: String| Diagnostics(vec![Diagnostic { path: path.to_path_buf(), line: 1, column: 1, message }]);
    let size = std::fs::metadata(path).map_err(|e| fail(format!("cannot read world file: {e}")))?.len();
    if size > MAX_WORLD_BYTES {
        return Err(fail(format!("world file is {size} bytes; at most {MAX_WORLD_BYTES} are allowed")));
    }
    let text = std::fs::read_to_string(path).map_err(|e| fail(format!("cannot read world file: {e}")))?;
    parse(path, &text)
}

/// Parses world-file `text`; `path` names it in diagnostics.
pub fn parse(path: &Path, text: &str) -> Result<World, Diagnostics> {
    let map = SourceMap::new(path, text);
    let mut errors = Vec::new();
    let (mut bounds, mut start, mut goal) = (None, None, None);
    let mut obstacles = Vec::new();
    let mut boxes = Vec::new();
    let mut offset = 0;
    for line in text.split_inclusive('\n') {
        let line_start = offset;
        offset += line.len();
        let content = line.split('#').next().unwrap_or("");
        let words: Vec<(usize, &str)> = content
            .split_ascii_whitespace()
            .map(|w| (line_start + (w.as_ptr() as usize - line.as_ptr() as usize), w))
            .collect();
        let Some(&(at, keyword)) = words.first() else { continue };
        let arity = match keyword {
            "bounds" | "wall" | "box" => 4,
            "start" | "goal" | "circle" => 3,
            _ => {
                errors.push(map.at(
                    at,
                    format!("unknown statement '{keyword}' (expected bounds, start, goal, wall, box or circle)"),
                ));
                continue;
            }
        };
        if words.len() != arity + 1 {
            errors.push(map.at(at, format!("'{keyword}' takes {arity} numbers, got {}", words.len() - 1)));
            continue;
        }
        let mut n = [0.0; 4];
        let mut ok = true;
        for (i, &(w_at, word)) in words[1..].iter().enumerate() {
            match word.parse::<f64>() {
                Ok(v) if v.is_finite() => n[i] = v,
                _ => {
                    errors.push(map.at(w_at, format!("'{word}' is not a finite number")));
                    ok = false;
                }
            }
        }
        if !ok {
            continue;
        }
        let p = |x: f64, y: f64| Point { x, y };
        let once = |slot: &mut Option<usize>, errors: &mut Vec<Diagnostic>| {
            if let Some(first) = slot.replace(at) {
                let (line, column) = map.line_column(first);
                errors.push(map.at(at, format!("'{keyword}' is already given at {line}:{column}")));
            }
        };
        match keyword {
            "bounds" => {
                let mut seen = bounds.map(|(_, at)| at);
                once(&mut seen, &mut errors);
                if n[2] <= n[0] || n[3] <= n[1] {
                    errors.push(map.at(at, "bounds need X1 > X0 and Y1 > Y0"));
                } else {
                    bounds = Some(((p(n[0], n[1]), p(n[2], n[3])), at));
                }
            }
            "start" => {
                let mut seen = start.map(|(_, at)| at);
                once(&mut seen, &mut errors);
                start = Some(((p(n[0], n[1]), n[2]), at));
            }
            "goal" => {
                let mut seen = goal.map(|(_, at)| at);
                once(&mut seen, &mut errors);
                if n[2] <= 0.0 {
                    errors.push(map.at(at, "the goal radius must be positive"));
                }
                goal = Some(((p(n[0], n[1]), n[2]), at));
            }
            "wall" => obstacles.push(Obstacle::Segment(p(n[0], n[1]), p(n[2], n[3]))),
            "box" => {
                if n[2] <= n[0] || n[3] <= n[1] {
                    errors.push(map.at(at, "a box needs X1 > X0 and Y1 > Y0"));
                } else {
                    obstacles.extend(rectangle(p(n[0], n[1]), p(n[2], n[3])));
                    boxes.push((p(n[0], n[1]), p(n[2], n[3])));
                }
            }
            _ => {
                if n[2] <= 0.0 {
                    errors.push(map.at(at, "a circle's radius must be positive"));
                } else {
                    obstacles.push(Obstacle::Circle(p(n[0], n[1]), n[2]));
                }
            }
        }
        if obstacles.len() > MAX_OBSTACLES {
            errors.push(map.at(at, format!("too many obstacles: at most {MAX_OBSTACLES}")));
            break;
        }
    }
    let end = text.len();
    for (name, missing) in [("bounds", bounds.is_none()), ("start", start.is_none()), ("goal", goal.is_none())] {
        if missing {
            errors.push(map.at(end, format!("missing '{name}' statement")));
        }
    }
    match (bounds, start, goal) {
        (Some((bounds, _)), Some((start, _)), Some((goal, _))) if errors.is_empty() => {
            obstacles.extend(rectangle(bounds.0, bounds.1));
            Ok(World { bounds, start, goal, obstacles, boxes })
        }
        _ => Err(Diagnostics(errors)),
    }
}

/// The four sides of an axis-aligned rectangle.
fn rectangle(a: Point, b: Point) -> [Obstacle; 4] {
    let (c, d) = (Point { x: b.x, y: a.y }, Point { x: a.x, y: b.y });
    [Obstacle::Segment(a, c), Obstacle::Segment(c, b), Obstacle::Segment(b, d), Obstacle::Segment(d, a)]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_world_parses_with_its_bounds_as_walls() {
        let text = "# demo\nbounds 0 0 10 8\nstart 1 1 0.5\ngoal 9 7 0.3   # there\nwall 4 0 4 5\nbox 6 3 7 4\ncircle 2 4 0.5\n";
        let world = parse(Path::new("w.world"), text).map_err(|e| e.to_string());
        let world = match world {
            Ok(w) => w,
            Err(e) => panic!("{e}"),
        };
        assert_eq!(world.start, (Point { x: 1.0, y: 1.0 }, 0.5));
        assert_eq!(world.goal, (Point { x: 9.0, y: 7.0 }, 0.3));
        // 1 wall + 4 box sides + 1 circle + 4 bounds.
        assert_eq!(world.obstacles.len(), 10);
    }

    #[test]
    fn every_error_is_reported_with_its_position() {
        let text = "bounds 0 0 10\nstart 1 x 0\nteleport 1 2\nbox 5 5 4 4\nstart 1 1 0\n";
        let errors = parse(Path::new("w.world"), text).err().map(|e| e.to_string()).unwrap_or_default();
        assert_eq!(
            errors,
            "w.world:1:1: 'bounds' takes 4 numbers, got 3\n\
             w.world:2:9: 'x' is not a finite number\n\
             w.world:3:1: unknown statement 'teleport' (expected bounds, start, goal, wall, box or circle)\n\
             w.world:4:1: a box needs X1 > X0 and Y1 > Y0\n\
             w.world:6:1: missing 'bounds' statement\n\
             w.world:6:1: missing 'goal' statement"
        );
    }
}

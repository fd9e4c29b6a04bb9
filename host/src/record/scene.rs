//! The simulated world in a recording (docs/recording.md, The world): each
//! `builtin:sim` component's world file as one `foxglove.SceneUpdate` on
//! [`SCENE_TOPIC`], written when a recording file opens and again when the
//! robot swaps to one with another world, so Foxglove's 3D panel shows the
//! walls, obstacles and goal around the recorded poses and scans.
//!
//! Entities (in the `world` frame, x and y as the world file has them,
//! z up from the floor), one per simulator `NAME`:
//! - `NAME/walls`: a cube per wall, box side and side of the bounds
//!   ([`WALL_THICKNESS_M`] thick, [`WALL_HEIGHT_M`] tall), centred on the
//!   segment and turned along it;
//! - `NAME/obstacles`: a cylinder per round obstacle;
//! - `NAME/goal`: a line loop around the goal, on the floor.

use std::path::Path;

use serde_json::{Value as Json, json};

use crate::builtin::builtin_of;
use crate::config::RobotConfig;
use crate::sim::world::{self, Obstacle, World};

/// The topic the world is written on, and its schema.
pub const SCENE_TOPIC: &str = "/world/scene";
pub const SCENE_UPDATE: &str = "foxglove.SceneUpdate";
/// How walls are drawn (the world file's walls are lines).
pub const WALL_THICKNESS_M: f64 = 0.05;
pub const WALL_HEIGHT_M: f64 = 0.3;
/// Round obstacles' height.
pub const OBSTACLE_HEIGHT_M: f64 = 0.3;
/// Points of the goal's ring.
const GOAL_POINTS: usize = 32;

/// The world files of `config`'s simulators: (component, world). A world
/// that does not load is left out (the simulator refuses it anyway).
pub fn worlds_of(config: &RobotConfig) -> Vec<(String, World)> {
    let base = config.path.parent().unwrap_or(Path::new(""));
    let mut worlds = Vec::new();
    for (index, component) in config.components.iter().enumerate() {
        let Some(param) = builtin_of(config, index, crate::assemble::registry::builtin).and_then(|b| b.world_param())
        else {
            continue;
        };
        let Some(file) = component.params.iter().find(|p| p.name == param) else { continue };
        if let Ok(world) = world::load(&base.join(file.value.trim())) {
            worlds.push((component.name.clone(), world));
        }
    }
    worlds
}

fn colour(r: f64, g: f64, b: f64) -> Json {
    json!({ "r": r, "g": g, "b": b, "a": 1.0 })
}

/// A pose at (x, y, z) turned by `yaw` about z.
fn pose(x: f64, y: f64, z: f64, yaw: f64) -> Json {
    json!({
        "position": { "x": x, "y": y, "z": z },
        "orientation": { "x": 0.0, "y": 0.0, "z": (yaw / 2.0).sin(), "w": (yaw / 2.0).cos() },
    })
}

fn entity(id: String, timestamp: &Json, shapes: Json) -> Json {
    let mut entity = json!({
        "timestamp": timestamp,
        "frame_id": super::schema::WORLD_FRAME,
        "id": id,
        "lifetime": { "sec": 0, "nsec": 0 },
        "frame_locked": false,
        "metadata": [],
        "arrows": [], "cubes": [], "spheres": [], "cylinders": [], "lines": [], "triangles": [], "texts": [],
        "models": [],
    });
    if let (Some(entity), Some(shapes)) = (entity.as_object_mut(), shapes.as_object()) {
        entity.extend(shapes.clone());
    }
    entity
}

/// `worlds` as one `foxglove.SceneUpdate` at `unix_ns`.
pub fn scene_update(worlds: &[(String, World)], unix_ns: u64) -> Json {
    let timestamp = super::schema::timestamp(unix_ns);
    let mut entities = Vec::new();
    for (name, world) in worlds {
        let mut walls = Vec::new();
        let mut cylinders = Vec::new();
        for obstacle in &world.obstacles {
            match *obstacle {
                Obstacle::Segment(a, b) => {
                    let (dx, dy) = (b.x - a.x, b.y - a.y);
                    walls.push(json!({
                        "pose": pose((a.x + b.x) / 2.0, (a.y + b.y) / 2.0, WALL_HEIGHT_M / 2.0, dy.atan2(dx)),
                        "size": { "x": dx.hypot(dy), "y": WALL_THICKNESS_M, "z": WALL_HEIGHT_M },
                        "color": colour(0.2, 0.2, 0.2),
                    }));
                }
                Obstacle::Circle(c, r) => cylinders.push(json!({
                    "pose": pose(c.x, c.y, OBSTACLE_HEIGHT_M / 2.0, 0.0),
                    "size": { "x": 2.0 * r, "y": 2.0 * r, "z": OBSTACLE_HEIGHT_M },
                    "bottom_scale": 1.0,
                    "top_scale": 1.0,
                    "color": colour(0.2, 0.2, 0.2),
                })),
            }
        }
        let (goal, radius) = world.goal;
        let ring: Vec<Json> = (0..GOAL_POINTS)
            .map(|i| {
                let angle = i as f64 * std::f64::consts::TAU / GOAL_POINTS as f64;
                json!({ "x": goal.x + radius * angle.cos(), "y": goal.y + radius * angle.sin(), "z": 0.0 })
            })
            .collect();
        entities.push(entity(format!("{name}/walls"), &timestamp, json!({ "cubes": walls })));
        entities.push(entity(format!("{name}/obstacles"), &timestamp, json!({ "cylinders": cylinders })));
        entities.push(entity(
            format!("{name}/goal"),
            &timestamp,
            json!({ "lines": [{
                "type": 1,
                "pose": pose(0.0, 0.0, 0.0, 0.0),
                "thickness": 0.03,
                "scale_invariant": false,
                "points": ring,
                "color": colour(0.1, 0.6, 0.2),
                "colors": [],
                "indices": [],
            }] }),
        ));
    }
    json!({ "deletions": [], "entities": entities })
}

/// `foxglove.SceneUpdate`'s JSON schema (the fields written here).
pub fn schema() -> Json {
    json!({
        "type": "object",
        "title": SCENE_UPDATE,
        "properties": {
            "deletions": { "type": "array", "items": { "type": "object" } },
            "entities": { "type": "array", "items": {
                "type": "object",
                "properties": {
                    "timestamp": { "type": "object" },
                    "frame_id": { "type": "string" },
                    "id": { "type": "string" },
                    "cubes": { "type": "array" },
                    "cylinders": { "type": "array" },
                    "lines": { "type": "array" },
                },
            } },
        },
        "required": ["deletions", "entities"],
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn each_wall_is_a_cube_along_it_and_each_circle_a_cylinder() {
        let world = world::parse(
            Path::new("t.world"),
            "bounds 0 0 4 2\nstart 1 1 0\ngoal 3 1 0.25\nwall 1 0 1 1\ncircle 2 1.5 0.2\n",
        )
        .unwrap();
        let scene = scene_update(&[("sim".into(), world)], 7);
        let entities = scene["entities"].as_array().unwrap();
        assert_eq!(entities.len(), 3);
        let cubes = entities[0]["cubes"].as_array().unwrap();
        assert_eq!(cubes.len(), 5, "4 bounds sides and a wall");
        let wall = cubes.iter().find(|c| c["size"]["x"] == 1.0 && c["pose"]["position"]["x"] == 1.0).unwrap();
        assert_eq!(wall["pose"]["position"]["y"], 0.5);
        let cylinder = &entities[1]["cylinders"][0];
        assert_eq!(
            (cylinder["pose"]["position"]["x"].as_f64(), cylinder["size"]["x"].as_f64()),
            (Some(2.0), Some(0.4))
        );
        assert_eq!(entities[2]["lines"][0]["points"].as_array().unwrap().len(), GOAL_POINTS);
    }
}

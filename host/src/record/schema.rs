//! What a recording's messages look like: the channels' JSON schemas
//! (Foxglove's well-known `foxglove.LaserScan`, `foxglove.PoseInFrame`,
//! `foxglove.FrameTransform` and `foxglove.Log` where they fit, subsume's
//! own otherwise) and the exact JSON form of a port value, which replay
//! reads back bit for bit (a number that is not finite is written as the
//! text `NaN`, `inf` or `-inf`).

use serde_json::{Map, Value as Json, json};

use crate::contract::{Scan, Value};

/// Schema names, as Foxglove and Lichtblick know them.
pub const LASER_SCAN: &str = "foxglove.LaserScan";
pub const POSE_IN_FRAME: &str = "foxglove.PoseInFrame";
pub const FRAME_TRANSFORM: &str = "foxglove.FrameTransform";
pub const COMPRESSED_IMAGE: &str = "foxglove.CompressedImage";
pub const LOG: &str = "foxglove.Log";
/// subsume's own schemas.
pub const VALUE: &str = "subsume.Value";
pub const CALL: &str = "subsume.Call";
pub const EVENT: &str = "subsume.Event";
pub const STATUS: &str = "subsume.Status";

/// The frame poses are given in, and the robot's own frame.
pub const WORLD_FRAME: &str = "world";
pub const ROBOT_FRAME: &str = "base_link";

/// A number as exact JSON: finite numbers as numbers, the rest as text.
pub fn number(x: f64) -> Json {
    if x.is_finite() {
        json!(x)
    } else if x.is_nan() {
        json!("NaN")
    } else if x > 0.0 {
        json!("inf")
    } else {
        json!("-inf")
    }
}

fn read_number(json: &Json) -> Option<f64> {
    match json {
        Json::Number(n) => n.as_f64(),
        Json::String(s) => match s.as_str() {
            "NaN" => Some(f64::NAN),
            "inf" => Some(f64::INFINITY),
            "-inf" => Some(f64::NEG_INFINITY),
            _ => None,
        },
        _ => None,
    }
}

fn numbers(xs: &[f64]) -> Json {
    Json::Array(xs.iter().map(|x| number(*x)).collect())
}

fn read_numbers(json: &Json) -> Option<Vec<f64>> {
    json.as_array()?.iter().map(read_number).collect()
}

/// A value in subsume's exact JSON form: `{"KIND": ...}`.
pub fn value_json(value: &Value) -> Json {
    match value {
        Value::Flag(b) => json!({ "flag": b }),
        Value::Scalar(x) => json!({ "scalar": number(*x) }),
        Value::Vector(v) => json!({ "vector": numbers(v) }),
        Value::Text(t) => json!({ "text": t }),
        Value::Command(c) => json!({ "command": c.text() }),
        Value::Bytes(b) => json!({ "bytes": hex::encode(b) }),
        Value::Scan(s) => json!({ "scan": {
            "angle_min": number(s.angle_min),
            "angle_increment": number(s.angle_increment),
            "range_min": number(s.range_min),
            "range_max": number(s.range_max),
            "ranges": numbers(&s.ranges),
        }}),
    }
}

/// Reads [`value_json`]'s form back; `None` when it is not one.
pub fn value_from_json(json: &Json) -> Option<Value> {
    let object = json.as_object()?;
    let (kind, inner) = object.iter().next()?;
    Some(match kind.as_str() {
        "flag" => Value::Flag(inner.as_bool()?),
        "scalar" => Value::Scalar(read_number(inner)?),
        "vector" => Value::Vector(read_numbers(inner)?),
        "text" => Value::Text(inner.as_str()?.to_string()),
        "command" => Value::Command(inner.as_str()?.into()),
        "bytes" => Value::Bytes(hex::decode(inner.as_str()?).ok()?),
        "scan" => Value::Scan(Scan {
            angle_min: read_number(inner.get("angle_min")?)?,
            angle_increment: read_number(inner.get("angle_increment")?)?,
            range_min: read_number(inner.get("range_min")?)?,
            range_max: read_number(inner.get("range_max")?)?,
            ranges: read_numbers(inner.get("ranges")?)?,
        }),
        _ => return None,
    })
}

/// Foxglove's time: `{sec, nsec}`.
pub fn timestamp(unix_ns: u64) -> Json {
    json!({ "sec": unix_ns / 1_000_000_000, "nsec": unix_ns % 1_000_000_000 })
}

/// A range scan as `foxglove.LaserScan`, plus subsume's fields that
/// Foxglove's message has no place for (`angle_increment`, `range_min`,
/// `range_max`), so replay gets the scan back exactly.
pub fn laser_scan(scan: &Scan, frame: &str, unix_ns: u64) -> Json {
    let rays = scan.ranges.len();
    let end = scan.angle_min + scan.angle_increment * rays.saturating_sub(1) as f64;
    json!({
        "timestamp": timestamp(unix_ns),
        "frame_id": frame,
        "pose": identity_pose(),
        "start_angle": number(scan.angle_min),
        "end_angle": number(end),
        "ranges": numbers(&scan.ranges),
        "intensities": [],
        "angle_increment": number(scan.angle_increment),
        "range_min": number(scan.range_min),
        "range_max": number(scan.range_max),
    })
}

/// Reads a [`laser_scan`] message back into the scan it was made from.
pub fn scan_from_laser_scan(json: &Json) -> Option<Value> {
    Some(Value::Scan(Scan {
        angle_min: read_number(json.get("start_angle")?)?,
        angle_increment: read_number(json.get("angle_increment")?)?,
        range_min: read_number(json.get("range_min")?)?,
        range_max: read_number(json.get("range_max")?)?,
        ranges: read_numbers(json.get("ranges")?)?,
    }))
}

fn identity_pose() -> Json {
    json!({ "position": { "x": 0.0, "y": 0.0, "z": 0.0 }, "orientation": { "x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0 } })
}

/// The quaternion of a turn by `heading` radians about z.
fn yaw(heading: f64) -> Json {
    json!({ "x": 0.0, "y": 0.0, "z": number((heading / 2.0).sin()), "w": number((heading / 2.0).cos()) })
}

/// A pose `[x, y, heading]` as `foxglove.PoseInFrame` in the world frame,
/// with the vector itself as `value` (exact, for replay).
pub fn pose_in_frame(pose: &[f64], unix_ns: u64) -> Json {
    let (x, y, heading) = (pose[0], pose[1], pose[2]);
    json!({
        "timestamp": timestamp(unix_ns),
        "frame_id": WORLD_FRAME,
        "pose": { "position": { "x": number(x), "y": number(y), "z": 0.0 }, "orientation": yaw(heading) },
        "value": numbers(pose),
    })
}

/// The same pose as the `world` -> `base_link` `foxglove.FrameTransform`.
pub fn frame_transform(pose: &[f64], unix_ns: u64) -> Json {
    json!({
        "timestamp": timestamp(unix_ns),
        "parent_frame_id": WORLD_FRAME,
        "child_frame_id": ROBOT_FRAME,
        "translation": { "x": number(pose[0]), "y": number(pose[1]), "z": 0.0 },
        "rotation": yaw(pose[2]),
    })
}

/// Reads a [`pose_in_frame`] message back into its vector.
pub fn vector_from_pose(json: &Json) -> Option<Value> {
    Some(Value::Vector(read_numbers(json.get("value")?)?))
}

/// A JPEG frame as `foxglove.CompressedImage` (its bytes base64, as
/// Foxglove's JSON encoding has them), taken at `capture_unix_ns`.
pub fn compressed_image(jpeg: &[u8], frame: &str, capture_unix_ns: u64) -> Json {
    use base64::Engine as _;
    json!({
        "timestamp": timestamp(capture_unix_ns),
        "frame_id": frame,
        "data": base64::engine::general_purpose::STANDARD.encode(jpeg),
        "format": "jpeg",
    })
}

/// Reads a [`compressed_image`] message back into its bytes.
pub fn bytes_from_compressed_image(json: &Json) -> Option<Value> {
    use base64::Engine as _;
    base64::engine::general_purpose::STANDARD.decode(json.get("data")?.as_str()?).ok().map(Value::Bytes)
}

/// `foxglove.Log`'s levels.
pub fn log_level(level: &tracing::Level) -> u8 {
    match *level {
        tracing::Level::TRACE | tracing::Level::DEBUG => 1,
        tracing::Level::INFO => 2,
        tracing::Level::WARN => 3,
        tracing::Level::ERROR => 4,
    }
}

/// A log line as `foxglove.Log`.
pub fn log(level: u8, name: &str, message: &str, unix_ns: u64) -> Json {
    json!({ "timestamp": timestamp(unix_ns), "level": level, "message": message, "name": name, "file": "", "line": 0 })
}

fn object(properties: Json, required: &[&str]) -> Json {
    json!({ "type": "object", "properties": properties, "required": required })
}

fn time_schema() -> Json {
    object(
        json!({ "sec": { "type": "integer", "minimum": 0 }, "nsec": { "type": "integer", "minimum": 0 } }),
        &["sec", "nsec"],
    )
}

fn vector3() -> Json {
    object(json!({ "x": { "type": "number" }, "y": { "type": "number" }, "z": { "type": "number" } }), &["x", "y", "z"])
}

fn quaternion() -> Json {
    object(
        json!({ "x": { "type": "number" }, "y": { "type": "number" }, "z": { "type": "number" }, "w": { "type": "number" } }),
        &["x", "y", "z", "w"],
    )
}

fn pose_schema() -> Json {
    object(json!({ "position": vector3(), "orientation": quaternion() }), &["position", "orientation"])
}

fn exact_number() -> Json {
    json!({ "type": ["number", "string"], "description": "a number; NaN, inf and -inf as text" })
}

fn value_schema() -> Json {
    json!({
        "type": "object",
        "description": "a port value: exactly one of its kinds",
        "minProperties": 1,
        "maxProperties": 1,
        "properties": {
            "flag": { "type": "boolean" },
            "scalar": exact_number(),
            "vector": { "type": "array", "items": exact_number() },
            "text": { "type": "string" },
            "command": { "type": "string", "description": "a standard control string" },
            "bytes": { "type": "string", "description": "hexadecimal" },
            "scan": { "type": "object" }
        }
    })
}

/// The JSON schema (`jsonschema` encoding) of the schema called `name`.
pub fn schema(name: &str) -> Json {
    let mut schema = match name {
        LASER_SCAN => object(
            json!({
                "timestamp": time_schema(),
                "frame_id": { "type": "string" },
                "pose": pose_schema(),
                "start_angle": exact_number(),
                "end_angle": exact_number(),
                "ranges": { "type": "array", "items": exact_number() },
                "intensities": { "type": "array", "items": { "type": "number" } },
                "angle_increment": exact_number(),
                "range_min": exact_number(),
                "range_max": exact_number(),
            }),
            &["timestamp", "frame_id", "pose", "start_angle", "end_angle", "ranges", "intensities"],
        ),
        POSE_IN_FRAME => object(
            json!({
                "timestamp": time_schema(),
                "frame_id": { "type": "string" },
                "pose": pose_schema(),
                "value": { "type": "array", "items": exact_number() },
            }),
            &["timestamp", "frame_id", "pose"],
        ),
        FRAME_TRANSFORM => object(
            json!({
                "timestamp": time_schema(),
                "parent_frame_id": { "type": "string" },
                "child_frame_id": { "type": "string" },
                "translation": vector3(),
                "rotation": quaternion(),
            }),
            &["timestamp", "parent_frame_id", "child_frame_id", "translation", "rotation"],
        ),
        COMPRESSED_IMAGE => object(
            json!({
                "timestamp": time_schema(),
                "frame_id": { "type": "string" },
                "data": { "type": "string", "contentEncoding": "base64" },
                "format": { "type": "string" },
            }),
            &["timestamp", "frame_id", "data", "format"],
        ),
        LOG => object(
            json!({
                "timestamp": time_schema(),
                "level": { "type": "integer", "minimum": 0, "maximum": 5 },
                "message": { "type": "string" },
                "name": { "type": "string" },
                "file": { "type": "string" },
                "line": { "type": "integer", "minimum": 0 },
            }),
            &["timestamp", "level", "message", "name", "file", "line"],
        ),
        CALL => object(
            json!({
                "t": { "type": "integer", "description": "graph time, ns since the host started" },
                "call": { "enum": ["tick", "input"] },
                "port": { "type": "integer" },
                "port_name": { "type": "string" },
                "from": { "type": "string" },
                "value": value_schema(),
            }),
            &["t", "call"],
        ),
        EVENT => object(
            json!({
                "t": { "type": "integer" },
                "component": { "type": "string" },
                "event": { "enum": ["fault", "restart"] },
                "reason": { "type": "string" },
                "attempt": { "type": "integer" },
            }),
            &["t", "component", "event"],
        ),
        STATUS => object(
            json!({
                "t": { "type": "integer" },
                "component": { "type": "string" },
                "kind": { "type": "string" },
                "status": { "type": "object" },
            }),
            &["t", "component", "kind", "status"],
        ),
        _ => object(json!({ "t": { "type": "integer" }, "value": value_schema() }), &["t", "value"]),
    };
    if let Some(map) = schema.as_object_mut() {
        let mut head = Map::new();
        head.insert("$schema".into(), json!("https://json-schema.org/draft/2020-12/schema"));
        head.insert("title".into(), json!(name));
        head.extend(std::mem::take(map));
        *map = head;
    }
    schema
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_picture_comes_back_bit_for_bit_with_its_capture_time() {
        let jpeg = vec![0xff, 0xd8, 0xff, 0xe0, 0, 1, 2, 254, 0xff, 0xd9];
        let image = compressed_image(&jpeg, "camera", 1_700_000_000_250_000_000);
        assert_eq!(image["timestamp"], json!({ "sec": 1_700_000_000u64, "nsec": 250_000_000u64 }));
        assert_eq!(image["format"], "jpeg");
        assert_eq!(bytes_from_compressed_image(&image), Some(Value::Bytes(jpeg)));
    }

    #[test]
    fn values_come_back_bit_for_bit() {
        let values = [
            Value::Flag(true),
            Value::Scalar(0.1 + 0.2),
            Value::Scalar(-0.0),
            Value::Vector(vec![1e-300, f64::NAN, f64::INFINITY, f64::NEG_INFINITY, 1.0 / 3.0]),
            Value::Text("a \"b\"\n".into()),
            Value::Command("VEL 0.2 0.1".into()),
            Value::Bytes(vec![0, 255, 7]),
            Value::Scan(Scan {
                angle_min: -std::f64::consts::FRAC_PI_2,
                angle_increment: std::f64::consts::FRAC_PI_8,
                range_min: 0.05,
                range_max: 4.0,
                ranges: vec![0.123456789012345, 4.0],
            }),
        ];
        for value in values {
            let text = serde_json::to_string(&value_json(&value)).unwrap();
            let back = value_from_json(&serde_json::from_str(&text).unwrap()).unwrap();
            assert_eq!(format!("{back:?}"), format!("{value:?}"), "{text}");
            let again = serde_json::to_string(&value_json(&back)).unwrap();
            assert_eq!(again, text);
        }
    }

    #[test]
    fn a_laser_scan_message_gives_its_scan_back() {
        let scan =
            Scan { angle_min: -1.2, angle_increment: 0.3, range_min: 0.1, range_max: 5.0, ranges: vec![1.0, 2.5] };
        let message = laser_scan(&scan, "motors", 1_500_000_000);
        assert_eq!(message["end_angle"], json!(-1.2 + 0.3));
        assert_eq!(message["timestamp"], json!({ "sec": 1, "nsec": 500_000_000 }));
        let back = scan_from_laser_scan(&serde_json::from_str(&message.to_string()).unwrap()).unwrap();
        assert_eq!(format!("{back:?}"), format!("{:?}", Value::Scan(scan)));
    }
}

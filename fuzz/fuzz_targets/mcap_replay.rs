//! Recordings read for replay (`subsume replay`, host/src/record/replay.rs):
//! any bytes after the MCAP magic to the MCAP reader with replay's options
//! (the `mcap` crate, the end magic not required: a cut file still
//! replays; given only the records whose lengths fit, `record/readable.rs`), and every message's JSON to the schema readers replay uses
//! (host/src/record/schema.rs): a recorded call's value, a `foxglove.LaserScan`,
//! a `foxglove.PoseInFrame`, a `subsume.Value`. No panic; what a reader
//! takes back is what writing it gives (`value_json`, `laser_scan`).
//! `read_recording`'s own matching of topics to components needs the
//! runtime's layouts: its cases are replay's unit tests.
#![no_main]
// The parser modules are shared with the host; not every item is used here.
#![allow(dead_code)]

include!("contract_mirror.rs");

#[path = "../../host/src/record/readable.rs"]
mod readable;
#[path = "../../host/src/record/schema.rs"]
mod schema;

use serde_json::Value as Json;

/// Most messages read of one input (replay reads them all; the fuzzer
/// needs its executions short).
const MAX_MESSAGES: usize = 64;

/// Reads `json` back through `from`, writes it with `to` and reads it again:
/// the two readings must agree (NaN included, hence the debug text).
fn round_trip(json: &Json, from: fn(&Json) -> Option<contract::Value>, to: fn(&contract::Value) -> Json) {
    if let Some(value) = from(json) {
        let again = from(&to(&value));
        assert_eq!(format!("{again:?}"), format!("{:?}", Some(&value)), "{json}");
    }
}

fn value_json(value: &contract::Value) -> Json {
    schema::value_json(value)
}

fn laser_scan(value: &contract::Value) -> Json {
    match value {
        contract::Value::Scan(scan) => schema::laser_scan(scan, "laser", 0),
        _ => unreachable!("scan_from_laser_scan reads scans only"),
    }
}

fn pose_in_frame(value: &contract::Value) -> Json {
    match value {
        contract::Value::Vector(pose) if pose.len() == 3 => schema::pose_in_frame(pose, 0),
        // A vector of another length is no pose; reading it back is the vector itself.
        contract::Value::Vector(v) => {
            serde_json::json!({ "value": v.iter().map(|x| schema::number(*x)).collect::<Vec<_>>() })
        }
        _ => unreachable!("vector_from_pose reads vectors only"),
    }
}

libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    let bytes = [mcap::MAGIC, data].concat();
    // What replay gives the reader (host/src/record/readable.rs).
    let readable = readable::readable(&bytes);
    if let Some(at) = readable.cut_at {
        assert_eq!(readable.bytes, &bytes[..at]);
    }
    let Ok(stream) = mcap::MessageStream::new_with_options(readable.bytes, mcap::read::Options::IgnoreEndMagic.into())
    else {
        return;
    };
    for message in stream.take(MAX_MESSAGES) {
        let Ok(message) = message else { break };
        let Ok(json) = serde_json::from_slice::<Json>(&message.data) else { continue };
        let schema_name = message.channel.schema.as_ref().map(|s| s.name.clone()).unwrap_or_default();
        match schema_name.as_str() {
            schema::LASER_SCAN => round_trip(&json, schema::scan_from_laser_scan, laser_scan),
            schema::POSE_IN_FRAME => round_trip(&json, schema::vector_from_pose, pose_in_frame),
            _ => {
                // A call (`{"t", "call", "port", "value"}`) or an output.
                let _ = (json["t"].as_u64(), json["call"].as_str(), json["port"].as_u64(), json["port_name"].as_str());
                round_trip(&json["value"], schema::value_from_json, value_json);
            }
        }
    }
});

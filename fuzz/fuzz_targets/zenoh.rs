//! Zenoh messages from peers (the ROS 2 face and host-to-host links): any
//! bytes to the value wire format (host/src/bridge/wire.rs) and to
//! rmw_zenoh's attachment (host/src/bridge/ros2.rs). No panic, nothing
//! past `MAX_VALUE_BYTES`; a value that decodes encodes to exactly the bytes
//! it came from (the format has one spelling per value) and fits a port of
//! its kind and no other; an attachment that decodes encodes to its bytes.
//! The CDR payloads have their own target (`cdr`).
#![no_main]
// The parser modules are shared with the host; not every item is used here.
#![allow(dead_code)]

#[path = "../../host/src/bridge"]
mod bridge {
    pub mod ros2;
    pub mod wire;
}

#[path = "../../host/src/robot/control.rs"]
mod control_impl;
mod robot {
    pub(crate) use crate::control_impl as control;
}

include!("contract_mirror.rs");

use bridge::{ros2, wire};
use contract::ValueKind;

const KINDS: [ValueKind; 8] = [
    ValueKind::Flag,
    ValueKind::Scalar,
    ValueKind::Vector,
    ValueKind::Text,
    ValueKind::Command,
    ValueKind::Bytes,
    ValueKind::Any,
    ValueKind::Scan,
];

libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    match wire::decode(data) {
        Ok(value) => {
            assert!(data.len() <= wire::MAX_VALUE_BYTES);
            assert_eq!(wire::encode(&value), data, "{value:?} has another spelling");
            for kind in KINDS {
                let fits = kind == ValueKind::Any || kind == contract::kind_of(&value);
                assert_eq!(wire::decode_as(data, kind).is_ok(), fits, "{value:?} as {kind}");
            }
        }
        Err(error) => {
            // A refusal names what was wrong in one short line.
            let text = error.to_string();
            assert!(!text.contains('\n') && text.len() <= 200, "{text:?}");
            assert!(KINDS.iter().all(|kind| wire::decode_as(data, *kind).is_err()));
        }
    }
    if let Some(attachment) = ros2::Attachment::decode(data) {
        assert_eq!(attachment.encode()[..], data[..]);
    }
});

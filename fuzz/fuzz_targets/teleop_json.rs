//! The teleoperation WebSocket's JSON messages: any text parses or is
//! refused with a bounded, one-line reason; what parses survives its own
//! JSON form.
#![no_main]
// The protocol modules are shared with the host; not every item is used here.
#![allow(dead_code)]

include!("teleop_common.rs");

libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    let Ok(text) = std::str::from_utf8(data) else { return };
    if text.len() > protocol::MAX_LINE_BYTES {
        // The session refuses longer messages before parsing.
        return;
    }
    match protocol::parse_json(text) {
        Ok(message) => {
            let json = to_json(&message);
            assert_eq!(protocol::parse_json(&json), Ok(message), "{json}");
        }
        Err(why) => check_refusal(&why),
    }
});

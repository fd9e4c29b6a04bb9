//! The teleoperation line protocol: any line parses or is refused with a
//! bounded, one-line reason; what parses means the same sent as JSON.
#![no_main]
// The protocol modules are shared with the host; not every item is used here.
#![allow(dead_code)]

include!("teleop_common.rs");

libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    let Ok(line) = std::str::from_utf8(data) else { return };
    if line.contains('\n') || line.len() > protocol::MAX_LINE_BYTES {
        // The line reader splits at '\n' and refuses longer lines first.
        return;
    }
    match protocol::parse_line(line) {
        Ok(message) => {
            let json = to_json(&message);
            assert_eq!(protocol::parse_json(&json), Ok(message), "{json}");
        }
        Err(why) => check_refusal(&why),
    }
});

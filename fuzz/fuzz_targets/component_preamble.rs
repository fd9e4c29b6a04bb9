//! Uploaded component bytes, first check: any bytes get a verdict, never a
//! panic, and only a component preamble passes.
#![no_main]
// The parser modules are shared with the host; not every item is used here.
#![allow(dead_code)]

#[path = "../../host/src/sandbox/preamble.rs"]
mod preamble;

libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    if preamble::check_component_preamble(data).is_ok() {
        assert!(data.starts_with(b"\0asm") && data.len() >= 8 && data[6..8] == [0x01, 0x00]);
    }
});

//! Control strings: parsing never panics, and what parses formats to a
//! string that parses back to the same command.
#![no_main]
// The parser modules are shared with the host; not every item is used here.
#![allow(dead_code)]

#[path = "../../host/src/robot/control.rs"]
mod control;
// The text clipper the parsers quote their input with (pure: the rest of
// `contract` is wasmtime bindgen output).
#[path = "../../host/src/contract/clip.rs"]
mod contract;

libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    let Ok(text) = std::str::from_utf8(data) else { return };
    if let Ok(command) = control::parse(text) {
        let canonical = command.to_string();
        assert_eq!(control::parse(&canonical), Ok(command), "{canonical}");
    }
});

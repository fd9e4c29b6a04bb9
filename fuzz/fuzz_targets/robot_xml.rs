//! Robot files, stage 1 (the file as written): any text yields diagnostics
//! or a tree, never a panic, and every diagnostic points inside the text.
//! (Stage 2 needs the component runtime; its cases are in tests/config.)
#![no_main]
// The parser modules are shared with the host; not every item is used here.
#![allow(dead_code)]

#[path = "../../host/src/config"]
mod config {
    pub mod diagnostic;
    pub mod raw;
}

use std::path::Path;

libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    let Ok(text) = std::str::from_utf8(data) else { return };
    let map = config::diagnostic::SourceMap::new(Path::new("fuzz.xml"), text);
    let mut errors = Vec::new();
    let _robot = config::raw::parse(&map, text, &mut errors);
    let lines = text.split('\n').count();
    for d in &errors {
        assert!(d.line >= 1 && d.line <= lines && d.column >= 1, "{d}");
    }
});

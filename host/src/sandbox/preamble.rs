//! The first check on bytes that claim to be a component: the eight-byte
//! preamble tells a WebAssembly component from a core module, a precompiled
//! native artifact (which is never loaded from outside) or anything else.
//! Pure, so it can be fuzzed without the runtime.

/// Why `bytes` are not a WebAssembly component, or `Ok` when the preamble
/// says they are (the compiler checks the rest).
pub fn check_component_preamble(bytes: &[u8]) -> Result<(), &'static str> {
    if bytes.starts_with(b"\x7fELF") {
        return Err(
            "this is a precompiled native artifact (ELF); upload the .wasm component itself: precompiled code is never loaded from outside",
        );
    }
    if !bytes.starts_with(b"\0asm") {
        return Err("the file does not start with the webassembly magic bytes '\\0asm'");
    }
    match bytes.get(4..8) {
        Some([0x01, 0x00, 0x00, 0x00]) => Err(
            "this is a core webassembly module, not a component (build for wasm32-wasip2, or wrap it with `wasm-tools component new`)",
        ),
        Some([_, _, 0x01, 0x00]) => Ok(()),
        Some(_) => Err("unknown webassembly version or layer in the preamble"),
        None => Err("the file is too short to be a webassembly component"),
    }
}

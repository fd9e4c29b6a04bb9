//! Lines from an ODrive (ASCII protocol answers) to the ODrive translator's
//! decoder (guest-components/rust/translator-odrive), built natively: no
//! panic, every reading finite, and the same readings and malformed count
//! however the bytes are cut (it decodes byte by byte).
#![no_main]

include!("translator_common.rs");

#[path = "../../guest-components/rust/translator-odrive/src/lib.rs"]
mod odrive;

const OPTION_SETS: &[&[(&str, &str)]] = &[
    &[("turns-per-metre", "10")],
    &[("turns-per-metre", "1e-300"), ("checksum", "on"), ("left-axis", "1"), ("left-sign", "-1")],
];

libfuzzer_sys::fuzz_target!(|data: &[u8]| check(data, odrive::fuzzing_translator, OPTION_SETS, true));

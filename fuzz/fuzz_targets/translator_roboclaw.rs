//! Bytes from a Basicmicro RoboClaw (acknowledgements and encoder answers) to
//! the RoboClaw translator's decoder (guest-components/rust/translator-roboclaw),
//! built natively: no panic, every reading finite, and the same readings
//! however the bytes are cut.
#![no_main]

include!("translator_common.rs");

#[path = "../../guest-components/rust/translator-roboclaw/src/lib.rs"]
mod roboclaw;

const OPTION_SETS: &[&[(&str, &str)]] =
    &[&[("counts-per-metre", "4000")], &[("counts-per-metre", "1e-300"), ("address", "135"), ("left", "m2")]];

libfuzzer_sys::fuzz_target!(|data: &[u8]| check(data, roboclaw::fuzzing_translator, OPTION_SETS, false));

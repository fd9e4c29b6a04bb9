//! Bytes from an iRobot Create 2 (its sensor stream) to the Create 2
//! translator's decoder (guest-components/rust/translator-create2), built
//! natively: no panic, every reading finite, and the same readings however
//! the bytes are cut.
#![no_main]

include!("translator_common.rs");

#[path = "../../guest-components/rust/translator-create2/src/lib.rs"]
mod create2;

const OPTION_SETS: &[&[(&str, &str)]] =
    &[&[], &[("light-bump-range", "0.5")], &[("mode", "full"), ("light-bump-range", "1e300")]];

libfuzzer_sys::fuzz_target!(|data: &[u8]| check(data, create2::fuzzing_translator, OPTION_SETS, false));

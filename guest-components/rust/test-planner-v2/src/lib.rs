//! Test guest for replay before activation: "version 2" of the planner
//! (guest-components/rust/planner), the same ports, parameters and steering,
//! but its commands carry two decimals instead of three. Replayed against a
//! recording of the planner, its `distance` outputs are identical and its
//! first `cmd` diverges.
//!
//! On every tick with a known pose it emits `VEL <v> <w>` that turns toward the
//! goal and slows down near it, and `STOP` once within `tolerance`. The goal
//! comes from the `goal-x`/`goal-y` parameters and can be changed at run time
//! on the `goal` input.

/// The name `describe` gives.
const NAME: &str = "test-planner-v2";
/// The summary `describe` gives.
const SUMMARY: &str = "Drives toward a goal position (commands with two decimals)";
/// Decimals of the speeds in `VEL` commands: the planner's three, less one.
const DECIMALS: usize = 2;

include!("../../planner/src/steer.rs");

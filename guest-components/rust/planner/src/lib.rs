//! Path planner (subsumption layer, default priority 1): steers toward a goal.
//!
//! On every tick with a known pose it emits `VEL <v> <w>` that turns toward the
//! goal and slows down near it, and `STOP` once within `tolerance`. The goal
//! comes from the `goal-x`/`goal-y` parameters and can be changed at run time
//! on the `goal` input.

/// The name `describe` gives.
const NAME: &str = "planner";
/// The summary `describe` gives.
const SUMMARY: &str = "Drives toward a goal position";
/// Decimals of the speeds in `VEL` commands.
const DECIMALS: usize = 3;

include!("steer.rs");

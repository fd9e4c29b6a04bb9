//! The robot side of motion (the control-string grammar is the contract's,
//! `contract::control`): the motor controllers' wire protocols, translators (the only code
//! that knows the hardware) and the serial link with its rate limit and
//! watchdog.

pub mod builtin;
pub mod device;
pub mod protocol;
pub mod serial;
pub mod translator;

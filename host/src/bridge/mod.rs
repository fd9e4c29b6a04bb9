//! Beyond one machine, over Zenoh: the sessions ([`session`]), ports
//! between subsume hosts (`builtin:zenoh`, `builtin:zenoh-publish`,
//! `builtin:zenoh-subscribe` in [`ports`], values encoded by [`wire`]), and
//! the ROS 2 face (`builtin:ros2-publish`, `builtin:ros2-subscribe` in
//! [`ros2_ports`]), speaking rmw_zenoh's wire format ([`ros2`]) with CDR
//! payloads ([`cdr`]). docs/distributed.md is the user's guide.
//!
//! Zenoh's runtime is its own: the control loop only ever touches the
//! bounded queues of [`link`] (drop-and-count when full), and what arrives
//! is untrusted (decoded off the loop; malformed payloads counted and
//! dropped; `wire` and `cdr` are fuzzed). A remote source is one more
//! component to the arbiter: its priority and timeout are the robot file's.

pub mod cdr;
pub mod link;
pub mod ports;
pub mod ros2;
pub mod ros2_ports;
pub mod session;
pub mod wire;

//! Every integration and end-to-end test, in one test binary: a module per
//! area, and [`support`] with what they share. One binary links the
//! library and its dependencies (wasmtime, Zenoh, the portal) once instead
//! of once per area.
//!
//! Run one area alone by its module: `cargo test --test all teleop::`, or
//! one test by its name: `cargo test --test all -- --exact
//! teleop::three_failed_logins_close_the_connection`.
//!
//! Every module's tests share this process, two at a time (libtest runs as
//! many threads as cores): nothing may assume it runs alone. [`support`]
//! keeps what is process-wide safe: one build of the guests, pseudo-terminals
//! that no other test's child process inherits, free ports, fresh folders.

#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic)]

mod support;

mod architecture;
mod builtins;
mod camera;
mod config_cases;
mod contracts;
mod controllers;
mod deploy;
mod e2e;
mod estop;
mod hostile;
mod ipcam;
mod lab;
mod lab_docs;
mod labnet;
mod labserver_router;
mod languages;
mod memory;
mod outputs;
mod ownership;
mod portal;
mod portal_router;
mod record;
mod replay;
mod ros2;
mod runtime;
mod schema;
mod scorer;
mod serial;
mod service;
mod simtime;
mod stall;
mod stops;
mod teleop;
mod translator;
mod zenoh;

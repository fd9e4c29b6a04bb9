//! subsume: a host that runs robot software as sandboxed WebAssembly
//! components, wired from an XML robot description.
//!
//! # Layout
//!
//! The binary (`main.rs`, one file per subcommand in `commands/`) parses
//! the command line and calls [`run::run`], the composition root. `ARCHITECTURE.md` maps the modules below, the
//! invariants each keeps, and the import rules between them (checked by
//! `tests/all/architecture.rs`). From the bottom up:
//!
//! - [`contract`], [`fsutil`], [`tls`], [`admission`]: the WIT contract's
//!   host side; atomic writes; TLS identities and the plain-text rule for
//!   listeners; bounded connection pools per client address and serving
//!   HTTP under them;
//! - [`runtime`]: the component trait, wiring, the graph and control loop;
//! - [`config`]: the robot file, as written and as validated;
//! - [`sandbox`]: wasmtime: engine, compile cache, guests and translators;
//! - [`store`]: blobs, sets, state, users and the audit log, one writer;
//! - [`builtin`]: the framework of native components;
//! - [`arbiter`], [`envelope`], [`robot`], [`sim`], [`camera`], [`teleop`], [`bridge`]:
//!   the built-ins and what they own (subsumption; the safety envelope;
//!   control strings, protocols, translators, the serial link; the
//!   simulated robot; its camera; the network platform; Zenoh ports and the ROS 2 face);
//! - [`assemble`]: robot file + loader -> a wired graph; the registry;
//! - [`report`]: the run report and the live status;
//! - [`metrics`]: the live status as Prometheus (OpenMetrics) text;
//! - [`deploy`]: the use cases (boot, upload, stage, activate, rollback);
//! - [`lab`]: the remote lab: experiments, the queue, preflight, results;
//! - [`portal`]: HTTP in front of `deploy`;
//! - [`run`], [`scaffold`]: `subsume run` and `subsume new`.

pub mod admission;
pub mod arbiter;
pub mod assemble;
pub mod bridge;
pub mod builtin;
pub mod camera;
pub mod config;
pub mod contract;
pub mod deploy;
pub mod envelope;
pub mod fsutil;
pub mod lab;
pub mod logfields;
pub mod metrics;
pub mod notify;
pub mod portal;
pub mod record;
pub mod report;
pub mod robot;
pub mod run;
pub mod runtime;
pub mod sandbox;
pub mod scaffold;
pub mod score;
pub mod sim;
pub mod store;
pub mod teleop;
pub mod tls;
pub mod walltime;

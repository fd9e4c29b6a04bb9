// Included by the targets whose parsers build the contract's values
// (zenoh, mcap_replay).
// The contract's value types are wasmtime bindgen output (host/src/contract.rs,
// from wit/robot.wit): this is their shape, for wire.rs to compile against.
// A variant the WIT adds and wire.rs handles fails this build, so the copy
// cannot drift silently. The kinds' logic and the clipper are the host's own.
#[path = "../../host/src/contract"]
mod contract {
    mod clip;
    mod kind;
    // Not every target uses every item.
    #[allow(unused_imports)]
    pub use clip::{MAX_QUOTED_BYTES, clip, clip_to};
    #[allow(unused_imports)]
    pub use kind::kind_of;

    #[derive(Clone, Debug, PartialEq)]
    pub struct Scan {
        pub angle_min: f64,
        pub angle_increment: f64,
        pub range_min: f64,
        pub range_max: f64,
        pub ranges: Vec<f64>,
    }

    #[derive(Clone, Debug, PartialEq)]
    pub enum Value {
        Flag(bool),
        Scalar(f64),
        Vector(Vec<f64>),
        Text(String),
        Command(String),
        Bytes(Vec<u8>),
        Scan(Scan),
    }

    #[derive(Clone, Copy, Debug, PartialEq, Eq)]
    pub enum ValueKind {
        Flag,
        Scalar,
        Vector,
        Text,
        Command,
        Bytes,
        Any,
        Scan,
    }
}

//! Test guest built against `subsume:robot@0.1.0` (`wit/0.1.0/robot.wit`):
//! the relay of `test-relay` (every input re-emitted on the output of the
//! same index) plus an `err` result for a negative scalar, so the tests see
//! a 0.1.0 component's values, results and errors beside 0.2.0 ones.

wit_bindgen::generate!({ world: "component", path: "../../../wit/0.1.0" });

use subsume::robot::host::emit;
use subsume::robot::types::{PortSpec, ValueKind};

struct RelayV1;

fn port(name: &str, kind: ValueKind, doc: &str) -> PortSpec {
    PortSpec { name: name.into(), kind, doc: doc.into() }
}

impl Guest for RelayV1 {
    fn describe() -> Description {
        Description {
            name: "test-relay-v1".into(),
            version: "0.1.0".into(),
            summary: "Forwards each input to the output of the same index (contract 0.1.0)".into(),
            inputs: vec![
                port("scalar-in", ValueKind::Scalar, "forwarded to scalar-out; negative: an err result"),
                port("vector-in", ValueKind::Vector, "forwarded to vector-out"),
            ],
            outputs: vec![
                port("scalar-out", ValueKind::Scalar, "what scalar-in received"),
                port("vector-out", ValueKind::Vector, "what vector-in received"),
            ],
            params: vec![],
            default_priority: None,
        }
    }

    fn init(_params: Vec<Param>) -> Result<(), String> {
        Ok(())
    }

    fn on_input(port: u32, value: Value) -> Result<(), String> {
        if let Value::Scalar(x) = value
            && x < 0.0
        {
            return Err(format!("negative input {x}"));
        }
        emit(port, &value);
        Ok(())
    }

    fn tick(_now_ns: u64) -> Result<(), String> {
        Ok(())
    }
}

export!(RelayV1);

//! Test and benchmark guest: re-emits every input value on the output with
//! the same index, unchanged (one hop guest -> host -> guest per value).

use subsume_guest::{Component, Description, Params, Value, ValueKind, emit, input, output};

struct Relay;

impl Component for Relay {
    fn describe() -> Description {
        Description::new("test-relay", "Forwards each input to the output of the same index")
            .input(input("scalar-in", ValueKind::Scalar, "forwarded to scalar-out"))
            .input(input("vector-in", ValueKind::Vector, "forwarded to vector-out"))
            .output(output("scalar-out", ValueKind::Scalar, "what scalar-in received"))
            .input(input("scan-in", ValueKind::Scan, "forwarded to scan-out, geometry and all"))
            .output(output("vector-out", ValueKind::Vector, "what vector-in received"))
            .output(output("scan-out", ValueKind::Scan, "what scan-in received"))
            .input(input("text-in", ValueKind::Text, "forwarded to text-out"))
            .output(output("text-out", ValueKind::Text, "what text-in received"))
    }
    fn init(_params: &Params) -> Result<Self, String> {
        Ok(Relay)
    }
    fn on_input(&mut self, port: u32, value: Value) -> Result<(), String> {
        emit(port, &value);
        Ok(())
    }
}

subsume_guest::component!(Relay);

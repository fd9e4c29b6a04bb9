// The teleoperation protocol (host/src/teleop/protocol.rs) and the modules
// it names, compiled on their own; included by the teleop_line and
// teleop_json targets.

#[path = "../../host/src/robot/control.rs"]
mod control_impl;
// The text clipper the parsers quote their input with (pure: the rest of
// `contract` is wasmtime bindgen output).
#[path = "../../host/src/contract/clip.rs"]
mod contract;
#[path = "../../host/src/teleop/mode.rs"]
mod mode_impl;
#[path = "../../host/src/teleop/protocol.rs"]
mod protocol;
#[path = "../../host/src/runtime/standing.rs"]
mod standing;

mod robot {
    pub(crate) use crate::control_impl as control;
}
mod teleop {
    pub(crate) use crate::mode_impl as mode;
}
mod runtime {
    pub(crate) use crate::standing::Standing;
}

use protocol::ClientMessage;

/// The JSON form of `message`, as docs/teleop.md writes it.
fn to_json(message: &ClientMessage) -> String {
    use serde_json::json;
    match message {
        ClientMessage::Auth { name, token } => json!({"type": "auth", "name": name, "token": token}),
        ClientMessage::Mode(mode) => json!({"type": "mode", "mode": mode.to_string()}),
        ClientMessage::Cmd { seq, time_ms, command } => {
            json!({"type": "cmd", "seq": seq, "time_ms": time_ms, "command": command.to_string()})
        }
        ClientMessage::Pong { nonce } => json!({"type": "pong", "nonce": nonce}),
        ClientMessage::Estop => json!({"type": "estop"}),
        ClientMessage::Release { lock: None } => json!({"type": "release"}),
        ClientMessage::Release { lock: Some(lock) } => json!({"type": "release", "lock": lock}),
        ClientMessage::Quit => json!({"type": "quit"}),
    }
    .to_string()
}

/// What the host answers a refused message with goes back to the operator
/// as one line: it must not hold a line break or another control character
/// (which would let a sender forge a host line), and it is bounded.
fn check_refusal(why: &str) {
    assert!(!why.is_empty());
    assert!(why.len() <= 2 * protocol::MAX_LINE_BYTES, "{} bytes", why.len());
    assert!(!why.chars().any(char::is_control), "{why:?}");
}

//! The teleoperation protocol's messages (docs/teleop.md), as text lines
//! (TCP) and as JSON objects (WebSocket). Parsing is strict and every error
//! is a sentence for the operator; nothing here does I/O.

use serde::Serialize;
use serde_json::json;

use crate::contract::clip;
use crate::contract::control::Command;
use crate::runtime::Standing;
use crate::teleop::mode::Mode;

/// Longest line (or WebSocket message) a client may send: a command is a
/// few dozen bytes; a longer line is refused and skipped, never buffered.
pub const MAX_LINE_BYTES: usize = 512;

/// What an operator sends.
#[derive(Clone, Debug, PartialEq)]
pub enum ClientMessage {
    Auth {
        name: String,
        token: String,
    },
    Mode(Mode),
    /// A motion command with the operator's sequence number and send time
    /// (milliseconds on the operator's clock).
    Cmd {
        seq: u64,
        time_ms: u64,
        /// Parsed here, once, and carried with the operator's text.
        command: Command,
    },
    Pong {
        nonce: u64,
    },
    /// Engage the emergency stop (docs/estop.md).
    Estop,
    /// Release a lock by name, or every engaged lock.
    Release {
        lock: Option<String>,
    },
    Quit,
}

/// What the host sends.
#[derive(Clone, Debug, PartialEq)]
pub enum ServerMessage {
    Hello {
        robot: String,
    },
    Ok(String),
    Error(String),
    Ping {
        nonce: u64,
    },
    Rtt {
        rtt_ms: f64,
        jitter_ms: f64,
        allowed: Vec<Mode>,
    },
    Mode {
        mode: Mode,
        reason: String,
    },
    Dropped {
        seq: u64,
        reason: String,
    },
    /// Whether the operator's commands drive the robot, told when it
    /// changes: `held`, `suppressed` (by `holder` at `priority`) or `idle`.
    Control {
        state: &'static str,
        holder: Option<(String, i32)>,
        message: String,
    },
}

/// Parses one protocol line.
pub(super) fn parse_line(line: &str) -> Result<ClientMessage, String> {
    let line = line.trim();
    let (keyword, rest) = line.split_once([' ', '\t']).map_or((line, ""), |(k, r)| (k, r.trim()));
    let words: Vec<&str> = rest.split_ascii_whitespace().collect();
    match keyword.to_ascii_uppercase().as_str() {
        "AUTH" => match words.as_slice() {
            [name, token] => Ok(ClientMessage::Auth { name: name.to_string(), token: token.to_string() }),
            _ => Err("AUTH takes a name and a token: AUTH <name> <token>".into()),
        },
        "MODE" => match words.as_slice() {
            [mode] => Mode::parse(mode)
                .map(ClientMessage::Mode)
                .ok_or_else(|| format!("unknown mode '{}': expected direct, shared or supervisory", clip(mode))),
            _ => Err("MODE takes one mode: MODE direct|shared|supervisory".into()),
        },
        "CMD" => {
            let mut parts = rest.splitn(3, [' ', '\t']);
            let (Some(seq), Some(time), Some(command)) = (parts.next(), parts.next(), parts.next()) else {
                return Err("CMD takes a sequence number, a time and a control string: CMD <seq> <ms> <command>".into());
            };
            let seq =
                seq.parse::<u64>().map_err(|_| format!("sequence number '{}' is not a whole number", clip(seq)))?;
            let time_ms = time
                .parse::<u64>()
                .map_err(|_| format!("time '{}' is not a whole number of milliseconds", clip(time)))?;
            let command = checked(Command::parse(command))?;
            Ok(ClientMessage::Cmd { seq, time_ms, command })
        }
        "PONG" => match words.as_slice() {
            [nonce] => nonce
                .parse::<u64>()
                .map(|nonce| ClientMessage::Pong { nonce })
                .map_err(|_| format!("nonce '{}' is not a whole number", clip(nonce))),
            _ => Err("PONG takes the nonce of the PING it answers: PONG <nonce>".into()),
        },
        "QUIT" if words.is_empty() => Ok(ClientMessage::Quit),
        "ESTOP" if words.is_empty() => Ok(ClientMessage::Estop),
        "ESTOP" => Err("ESTOP takes nothing: ESTOP".into()),
        "RELEASE" => match words.as_slice() {
            [] => Ok(ClientMessage::Release { lock: None }),
            [lock] => Ok(ClientMessage::Release { lock: Some(lock.to_string()) }),
            _ => Err("RELEASE takes at most a lock's name: RELEASE [lock]".into()),
        },
        "" => Err("empty line".into()),
        other => {
            Err(format!("unknown message '{}': expected AUTH, MODE, CMD, PONG, ESTOP, RELEASE or QUIT", clip(other)))
        }
    }
}

/// `command` if its text parsed; an operator's bad line is refused here.
fn checked(command: Command) -> Result<Command, String> {
    match command.parsed() {
        Ok(_) => Ok(command),
        Err(e) => Err(format!("bad control string: {e}")),
    }
}

/// Parses one JSON message: `{"type": "auth", "name": .., "token": ..}`,
/// `{"type": "mode", "mode": ..}`, `{"type": "cmd", "seq": .., "time_ms": ..,
/// "command": ..}`, `{"type": "pong", "nonce": ..}`, `{"type": "estop"}`,
/// `{"type": "release"}` (or with `"lock": ..`), `{"type": "quit"}`.
pub(super) fn parse_json(text: &str) -> Result<ClientMessage, String> {
    let value: serde_json::Value = serde_json::from_str(text).map_err(|e| format!("not a JSON object: {e}"))?;
    let field = |name: &str| value.get(name).ok_or_else(|| format!("missing field '{name}'"));
    let text_field = |name: &str| {
        field(name)?.as_str().map(str::to_string).ok_or_else(|| format!("field '{name}' must be a string"))
    };
    let number_field =
        |name: &str| field(name)?.as_u64().ok_or_else(|| format!("field '{name}' must be a whole number"));
    match value.get("type").and_then(|t| t.as_str()) {
        Some("auth") => Ok(ClientMessage::Auth { name: text_field("name")?, token: text_field("token")? }),
        Some("mode") => {
            let mode = text_field("mode")?;
            Mode::parse(&mode)
                .map(ClientMessage::Mode)
                .ok_or_else(|| format!("unknown mode '{}': expected direct, shared or supervisory", clip(&mode)))
        }
        Some("cmd") => {
            let command = checked(Command::parse(&text_field("command")?))?;
            Ok(ClientMessage::Cmd { seq: number_field("seq")?, time_ms: number_field("time_ms")?, command })
        }
        Some("pong") => Ok(ClientMessage::Pong { nonce: number_field("nonce")? }),
        Some("quit") => Ok(ClientMessage::Quit),
        Some("estop") => Ok(ClientMessage::Estop),
        Some("release") => match value.get("lock") {
            None | Some(serde_json::Value::Null) => Ok(ClientMessage::Release { lock: None }),
            Some(_) => Ok(ClientMessage::Release { lock: Some(text_field("lock")?) }),
        },
        Some(other) => Err(format!(
            "unknown message type '{}': expected auth, mode, cmd, pong, estop, release or quit",
            clip(other)
        )),
        None => Err("missing field 'type'".into()),
    }
}

impl ServerMessage {
    /// The message as a protocol line (without the newline).
    pub fn to_line(&self) -> String {
        match self {
            ServerMessage::Hello { robot } => format!("HELLO subsume {} robot={robot}", env!("CARGO_PKG_VERSION")),
            ServerMessage::Ok(text) => format!("OK {text}"),
            ServerMessage::Error(text) => format!("ERR {text}"),
            ServerMessage::Ping { nonce } => format!("PING {nonce}"),
            ServerMessage::Rtt { rtt_ms, jitter_ms, allowed } => {
                let allowed: Vec<&str> = allowed.iter().map(|m| m.name()).collect();
                format!("RTT {rtt_ms:.1} JITTER {jitter_ms:.1} ALLOWED {}", allowed.join(","))
            }
            ServerMessage::Mode { mode, reason } => format!("MODE {mode} {reason}"),
            ServerMessage::Dropped { seq, reason } => format!("DROP {seq} {reason}"),
            ServerMessage::Control { state, holder: Some((name, priority)), message } => {
                format!("CONTROL {state} {name} {priority} {message}")
            }
            ServerMessage::Control { state, holder: None, message } => format!("CONTROL {state} {message}"),
        }
    }

    /// The message as a JSON object.
    pub fn to_json(&self) -> String {
        let value = match self {
            ServerMessage::Hello { robot } => {
                json!({"type": "hello", "robot": robot, "version": env!("CARGO_PKG_VERSION")})
            }
            ServerMessage::Ok(text) => json!({"type": "ok", "message": text}),
            ServerMessage::Error(text) => json!({"type": "error", "message": text}),
            ServerMessage::Ping { nonce } => json!({"type": "ping", "nonce": nonce}),
            ServerMessage::Rtt { rtt_ms, jitter_ms, allowed } => {
                json!({"type": "rtt", "rtt_ms": rtt_ms, "jitter_ms": jitter_ms, "allowed": allowed})
            }
            ServerMessage::Mode { mode, reason } => json!({"type": "mode", "mode": mode, "reason": reason}),
            ServerMessage::Dropped { seq, reason } => json!({"type": "drop", "seq": seq, "reason": reason}),
            ServerMessage::Control { state, holder, message } => json!({
                "type": "control",
                "state": state,
                "holder": holder.as_ref().map(|(name, _)| name),
                "priority": holder.as_ref().map(|(_, priority)| priority),
                "message": message,
            }),
        };
        value.to_string()
    }
}

/// What the operator is told about `standing`, in `mode`, whose source
/// has `base` priority plus the mode's offset (operators win ties).
pub fn control_message(standing: &Standing, mode: Option<Mode>, base: i32) -> ServerMessage {
    match standing {
        Standing::Holds => {
            ServerMessage::Control { state: "held", holder: None, message: "your commands drive the robot".into() }
        }
        Standing::Idle => ServerMessage::Control {
            state: "idle",
            holder: None,
            message: "no command of yours is driving the robot".into(),
        },
        Standing::Suppressed { by, priority } => {
            let winning: Vec<&str> = Mode::ALL
                .into_iter()
                .filter(|m| Some(*m) != mode && base + m.priority_offset() >= *priority)
                .map(Mode::name)
                .collect();
            let hint = match winning.as_slice() {
                [] => "no control mode outranks it".to_string(),
                [one] => format!("{one} mode would win"),
                several => format!("{} mode would win", several.join(" or ")),
            };
            ServerMessage::Control {
                state: "suppressed",
                holder: Some((by.clone(), *priority)),
                message: format!("suppressed by {by} (priority {priority}): {hint}"),
            }
        }
    }
}

/// A session's summary for the report.
#[derive(Clone, Debug, Default, Serialize)]
pub struct ModeChange {
    pub at_s: f64,
    pub from: Option<Mode>,
    pub to: Option<Mode>,
    pub reason: String,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lines_parse_into_messages() {
        let cases = [
            ("AUTH alice s3cret", ClientMessage::Auth { name: "alice".into(), token: "s3cret".into() }),
            ("mode shared", ClientMessage::Mode(Mode::Shared)),
            ("CMD 7 1234 VEL 0.2 -0.1", ClientMessage::Cmd { seq: 7, time_ms: 1234, command: "VEL 0.2 -0.1".into() }),
            ("PONG 42", ClientMessage::Pong { nonce: 42 }),
            ("QUIT", ClientMessage::Quit),
            ("ESTOP", ClientMessage::Estop),
            ("release", ClientMessage::Release { lock: None }),
            ("RELEASE bumper", ClientMessage::Release { lock: Some("bumper".into()) }),
        ];
        for (line, expected) in cases {
            assert_eq!(parse_line(line), Ok(expected), "{line}");
        }
    }

    #[test]
    fn bad_lines_say_why() {
        let cases = [
            ("", "empty line"),
            ("HELLO", "unknown message 'HELLO': expected AUTH, MODE, CMD, PONG, ESTOP, RELEASE or QUIT"),
            ("AUTH alice", "AUTH takes a name and a token: AUTH <name> <token>"),
            ("MODE manual", "unknown mode 'manual': expected direct, shared or supervisory"),
            ("CMD 1 2", "CMD takes a sequence number, a time and a control string: CMD <seq> <ms> <command>"),
            ("CMD x 2 STOP", "sequence number 'x' is not a whole number"),
            ("CMD 1 -2 STOP", "time '-2' is not a whole number of milliseconds"),
            ("CMD 1 2 FLY", "bad control string: column 1: unknown command 'FLY': expected STOP, VEL or GOTO"),
            ("PONG", "PONG takes the nonce of the PING it answers: PONG <nonce>"),
        ];
        for (line, expected) in cases {
            assert_eq!(parse_line(line), Err(expected.to_string()), "{line:?}");
        }
    }

    #[test]
    fn json_messages_mirror_the_lines() {
        assert_eq!(
            parse_json(r#"{"type":"cmd","seq":3,"time_ms":10,"command":"STOP"}"#),
            Ok(ClientMessage::Cmd { seq: 3, time_ms: 10, command: "STOP".into() })
        );
        assert_eq!(parse_json(r#"{"type":"mode","mode":"direct"}"#), Ok(ClientMessage::Mode(Mode::Direct)));
        assert_eq!(parse_json(r#"{"type":"pong"}"#), Err("missing field 'nonce'".into()));
        assert_eq!(parse_json(r#"{"type":"estop"}"#), Ok(ClientMessage::Estop));
        assert_eq!(parse_json(r#"{"type":"release"}"#), Ok(ClientMessage::Release { lock: None }));
        assert_eq!(
            parse_json(r#"{"type":"release","lock":"bumper"}"#),
            Ok(ClientMessage::Release { lock: Some("bumper".into()) })
        );
        assert_eq!(parse_json(r#"{"type":"release","lock":3}"#), Err("field 'lock' must be a string".into()));
        assert!(parse_json("[1").is_err_and(|e| e.starts_with("not a JSON object")));
        let rtt = ServerMessage::Rtt { rtt_ms: 42.0, jitter_ms: 1.5, allowed: vec![Mode::Direct, Mode::Shared] };
        assert_eq!(rtt.to_line(), "RTT 42.0 JITTER 1.5 ALLOWED direct,shared");
        assert_eq!(rtt.to_json(), r#"{"allowed":["direct","shared"],"jitter_ms":1.5,"rtt_ms":42.0,"type":"rtt"}"#);
    }

    #[test]
    fn control_notices_say_who_holds_and_which_mode_would_win() {
        let planner = Standing::Suppressed { by: "planner".into(), priority: 1 };
        let avoid = Standing::Suppressed { by: "avoid".into(), priority: 3 };
        let cases = [
            (
                &planner,
                Some(Mode::Supervisory),
                "CONTROL suppressed planner 1 suppressed by planner (priority 1): direct or shared mode would win",
            ),
            (
                &planner,
                Some(Mode::Direct),
                "CONTROL suppressed planner 1 suppressed by planner (priority 1): shared mode would win",
            ),
            (
                &avoid,
                Some(Mode::Shared),
                "CONTROL suppressed avoid 3 suppressed by avoid (priority 3): no control mode outranks it",
            ),
            (&Standing::Holds, Some(Mode::Direct), "CONTROL held your commands drive the robot"),
            (&Standing::Idle, None, "CONTROL idle no command of yours is driving the robot"),
        ];
        for (standing, mode, line) in cases {
            assert_eq!(control_message(standing, mode, 1).to_line(), line);
        }
        assert_eq!(
            control_message(&avoid, Some(Mode::Shared), 1).to_json(),
            r#"{"holder":"avoid","message":"suppressed by avoid (priority 3): no control mode outranks it","priority":3,"state":"suppressed","type":"control"}"#
        );
    }
}

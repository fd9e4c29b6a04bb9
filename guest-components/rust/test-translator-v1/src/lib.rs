//! Test translator built against `subsume:robot@0.1.0`: the readable ASCII
//! motor protocol of docs/protocols.md (`M <left mm/s> <right mm/s>`, `S`;
//! feedback `O x y heading` in thousandths, `B 0|1`), kept small: enough for
//! the tests to drive a simulated robot through a 0.1.0 translator.

wit_bindgen::generate!({ world: "translator", path: "../../../wit/0.1.0" });

use subsume::robot::types::{Feedback, Pose};

/// Longest line kept; longer ones are garbage.
const MAX_LINE: usize = 256;

struct AsciiV1;

static STATE: std::sync::Mutex<(f64, Vec<u8>)> = std::sync::Mutex::new((0.3, Vec::new()));

fn milli(value: f64) -> i64 {
    if value.is_finite() { (value * 1000.0).round() as i64 } else { 0 }
}

impl Guest for AsciiV1 {
    fn init(params: Vec<Param>) -> Result<(), String> {
        let wheel_base = match params.iter().find(|p| p.name == "wheel-base") {
            Some(p) => {
                p.value.trim().parse::<f64>().map_err(|_| format!("wheel-base '{}' is not a number", p.value))?
            }
            None => 0.3,
        };
        let mut state = STATE.lock().map_err(|_| "state poisoned".to_string())?;
        state.0 = wheel_base;
        Ok(())
    }

    fn encode(command: String) -> Result<Vec<u8>, String> {
        let wheel_base = STATE.lock().map(|s| s.0).unwrap_or(0.3);
        let words: Vec<&str> = command.split_whitespace().collect();
        match words.as_slice() {
            ["STOP"] => Ok(b"S\n".to_vec()),
            ["VEL", v, w] => {
                let v: f64 = v.parse().map_err(|_| format!("bad speed in '{command}'"))?;
                let w: f64 = w.parse().map_err(|_| format!("bad turn rate in '{command}'"))?;
                let half = w * wheel_base / 2.0;
                Ok(format!("M {} {}\n", milli(v - half), milli(v + half)).into_bytes())
            }
            _ => Err(format!("'{command}' cannot be sent to the motors")),
        }
    }

    fn decode(bytes: Vec<u8>) -> Decoded {
        let mut decoded = Decoded { feedback: Vec::new(), malformed: 0 };
        let Ok(mut state) = STATE.lock() else { return decoded };
        for byte in bytes {
            if byte != b'\n' {
                if state.1.len() < MAX_LINE {
                    state.1.push(byte);
                }
                continue;
            }
            let line = String::from_utf8_lossy(&state.1).into_owned();
            state.1.clear();
            let words: Vec<&str> = line.split_whitespace().collect();
            let number = |w: &str| w.parse::<i64>().ok().map(|x| x as f64 / 1000.0);
            match words.as_slice() {
                ["O", x, y, h] => match (number(x), number(y), number(h)) {
                    (Some(x), Some(y), Some(heading)) => {
                        decoded.feedback.push(Feedback::Odometry(Pose { x, y, heading }))
                    }
                    _ => decoded.malformed += 1,
                },
                ["B", "0"] => decoded.feedback.push(Feedback::Bumper(false)),
                ["B", "1"] => decoded.feedback.push(Feedback::Bumper(true)),
                // Ranges and battery lines: not this test translator's business.
                ["R", ..] | ["P", _] => {}
                _ => decoded.malformed += 1,
            }
        }
        decoded
    }
}

export!(AsciiV1);

//! Translators: the only code that knows the hardware. A translator turns the
//! winning control string into the motor controller's bytes and the
//! controller's bytes back into feedback. Supporting a new robot means a new
//! translator (a built-in profile here, or a WASM translator component),
//! nothing else.

use super::protocol::{Decoder, Feedback, Message, MotorCommand, Profile};
use crate::contract::bindings::subsume::robot::types::Feedback as WitFeedback;
use crate::contract::control::ControlCommand;
use crate::sandbox::{TranslatorCallError, WasmTranslator};

/// Why a translator produced no bytes.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum TranslateError {
    /// The hardware cannot carry this command (e.g. GOTO): nothing is sent.
    #[error("{0}")]
    Refused(String),
    /// The translator itself broke (a WASM translator trapped or overran its
    /// budget): the link stops.
    #[error("the translator faulted: {0}")]
    Fault(String),
}

/// Turns commands into bytes for one motor controller and its bytes back
/// into feedback.
pub trait Translator: Send {
    /// Appends the bytes for `command` to `out`.
    fn encode(&mut self, command: &ControlCommand, out: &mut Vec<u8>) -> Result<(), TranslateError>;
    /// Decodes whatever `bytes` complete into `out`. `Err` (a fault) only
    /// when the translator itself broke.
    fn decode(&mut self, bytes: &[u8], out: &mut Vec<Feedback>) -> Result<(), TranslateError>;
    /// Bytes or messages from the controller skipped as malformed.
    fn malformed(&self) -> u64;
    /// What the link sends on opening and closing the device, and how often
    /// it polls. The default (the built-in profiles): nothing.
    fn plan(&self) -> LinkPlan {
        LinkPlan::default()
    }
    /// Appends the bytes a poll at `now_ns` asks to send (a sensor request,
    /// a keep-alive). `Err` (a fault) only when the translator broke.
    fn poll(&mut self, now_ns: u64, out: &mut Vec<u8>) -> Result<(), TranslateError> {
        let _ = (now_ns, out);
        Ok(())
    }
}

/// What a translator needs from the link besides `encode` and `decode`.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct LinkPlan {
    /// Sent every time the device opens, before any command.
    pub opening: Vec<u8>,
    /// How often `poll` is called, nanoseconds; 0: never.
    pub poll_period_ns: u64,
    /// Sent after the final STOP, when the link closes.
    pub closing: Vec<u8>,
}

/// Geometry of a differential-drive base.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DriveGeometry {
    /// Distance between the wheels, metres.
    pub wheel_base: f64,
    /// Fastest wheel surface speed, m/s: commands are scaled down to fit.
    pub max_wheel_speed: f64,
}

impl DriveGeometry {
    /// Wheel speeds for a body twist, scaled down together (keeping the
    /// curvature) when a wheel would exceed `max_wheel_speed`.
    pub fn wheels(&self, linear: f64, angular: f64) -> (f64, f64) {
        let half = angular * self.wheel_base / 2.0;
        let (left, right) = (linear - half, linear + half);
        let fastest = left.abs().max(right.abs());
        if fastest > self.max_wheel_speed && fastest > 0.0 {
            let scale = self.max_wheel_speed / fastest;
            (left * scale, right * scale)
        } else {
            (left, right)
        }
    }

    /// The body twist (linear m/s, angular rad/s) of two wheel speeds.
    pub fn twist(&self, left: f64, right: f64) -> (f64, f64) {
        ((left + right) / 2.0, (right - left) / self.wheel_base)
    }
}

/// A translator for a built-in wire profile.
#[derive(Debug)]
pub struct ProfileTranslator {
    profile: Profile,
    geometry: DriveGeometry,
    decoder: Decoder,
    unexpected: u64,
    messages: Vec<Message>,
}

impl ProfileTranslator {
    pub fn new(profile: Profile, geometry: DriveGeometry) -> ProfileTranslator {
        ProfileTranslator { profile, geometry, decoder: Decoder::new(profile), unexpected: 0, messages: Vec::new() }
    }
}

impl Translator for ProfileTranslator {
    fn encode(&mut self, command: &ControlCommand, out: &mut Vec<u8>) -> Result<(), TranslateError> {
        let motor = match *command {
            ControlCommand::Stop => MotorCommand::Stop,
            ControlCommand::Vel { linear, angular } => {
                let (left, right) = self.geometry.wheels(linear, angular);
                MotorCommand::Wheels { left, right }
            }
            ControlCommand::Goto { .. } => {
                return Err(TranslateError::Refused(
                    "GOTO is a goal for a planner; the motors take VEL and STOP".into(),
                ));
            }
        };
        self.profile.encode_command(&motor, out);
        Ok(())
    }

    fn decode(&mut self, bytes: &[u8], out: &mut Vec<Feedback>) -> Result<(), TranslateError> {
        self.decoder.feed(bytes, &mut self.messages);
        for message in self.messages.drain(..) {
            match message {
                Message::Feedback(feedback) => out.push(feedback),
                // A controller does not send commands: count it as garbage.
                Message::Command(_) => self.unexpected += 1,
            }
        }
        Ok(())
    }

    fn malformed(&self) -> u64 {
        self.decoder.malformed() + self.unexpected
    }
}

/// A WASM component of the `translator` world, as the link's translator.
impl Translator for WasmTranslator {
    fn encode(&mut self, command: &ControlCommand, out: &mut Vec<u8>) -> Result<(), TranslateError> {
        WasmTranslator::encode(self, &command.to_string(), out).map_err(|e| match e {
            TranslatorCallError::Refused(why) => TranslateError::Refused(why),
            TranslatorCallError::Broken(why) => TranslateError::Fault(why),
        })
    }

    fn decode(&mut self, bytes: &[u8], out: &mut Vec<Feedback>) -> Result<(), TranslateError> {
        let (feedback, fault) =
            WasmTranslator::decode(self, bytes).map_err(|e| TranslateError::Fault(e.to_string()))?;
        out.extend(feedback.into_iter().map(|f| match f {
            WitFeedback::Odometry(p) => Feedback::Odometry { x: p.x, y: p.y, heading: p.heading },
            WitFeedback::Ranges(r) => Feedback::Ranges(r),
            WitFeedback::Bumper(b) => Feedback::Bumper(b),
            WitFeedback::Battery(v) => Feedback::Battery(v),
            // The link's `ranges` output carries the readings; the geometry
            // is the link's own (see docs/protocols.md).
            WitFeedback::Scan(s) => Feedback::Ranges(s.ranges),
        }));
        // The controller's fault status, reported during the call (see
        // `sandbox::translator`): its text, empty for none.
        if let Some(text) = fault {
            let text = text.trim();
            out.push(Feedback::Fault((!text.is_empty()).then(|| text.to_string())));
        }
        Ok(())
    }

    fn malformed(&self) -> u64 {
        WasmTranslator::malformed(self)
    }

    fn plan(&self) -> LinkPlan {
        let plan = WasmTranslator::plan(self);
        LinkPlan {
            opening: plan.opening.clone(),
            poll_period_ns: u64::from(plan.poll_period_ms) * 1_000_000,
            closing: plan.closing.clone(),
        }
    }

    fn poll(&mut self, now_ns: u64, out: &mut Vec<u8>) -> Result<(), TranslateError> {
        WasmTranslator::poll(self, now_ns, out).map_err(|e| TranslateError::Fault(e.to_string()))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const GEOMETRY: DriveGeometry = DriveGeometry { wheel_base: 0.3, max_wheel_speed: 0.5 };

    fn bytes(profile: Profile, command: &str) -> Result<Vec<u8>, String> {
        let mut translator = ProfileTranslator::new(profile, GEOMETRY);
        let command: ControlCommand = command.parse().map_err(|e| format!("{e}"))?;
        let mut out = Vec::new();
        translator.encode(&command, &mut out).map_err(|e| e.to_string())?;
        Ok(out)
    }

    /// Golden bytes, per profile: control string in, serial bytes out.
    #[test]
    fn control_strings_become_the_profiles_bytes() {
        let cases: [(&str, &[u8], &[u8]); 4] = [
            ("STOP", b"S\n", &[0xA5, 0x01, 0x02, 0xFE]),
            // 0.2 m/s straight: both wheels 200 mm/s (0x00C8).
            ("VEL 0.2 0", b"M 200 200\n", &[0xA5, 0x05, 0x01, 0xC8, 0x00, 0xC8, 0x00, 0x6F]),
            // Turning on the spot at 1 rad/s: wheels -/+ 150 mm/s.
            ("VEL 0 1", b"M -150 150\n", &[0xA5, 0x05, 0x01, 0x6A, 0xFF, 0x96, 0x00, 0x00]),
            // 1 m/s + 2 rad/s would need 1.3 m/s on a wheel: scaled to 0.5.
            ("VEL 1 2", b"M 269 500\n", &[0xA5, 0x05, 0x01, 0x0D, 0x01, 0xF4, 0x01, 0xFC]),
        ];
        for (command, ascii, binary) in cases {
            assert_eq!(bytes(Profile::Ascii, command).as_deref(), Ok(ascii), "{command}");
            assert_eq!(bytes(Profile::Binary, command).as_deref(), Ok(binary), "{command}");
        }
        assert!(bytes(Profile::Ascii, "GOTO 1 2").is_err_and(|e| e.contains("planner")));
    }

    #[test]
    fn feedback_is_decoded_and_commands_from_the_controller_are_garbage() {
        let mut translator = ProfileTranslator::new(Profile::Ascii, GEOMETRY);
        let mut out = Vec::new();
        assert_eq!(translator.decode(b"O 1000 2000 500\nS\nB 1\n", &mut out), Ok(()));
        assert_eq!(out, vec![Feedback::Odometry { x: 1.0, y: 2.0, heading: 0.5 }, Feedback::Bumper(true)]);
        assert_eq!(translator.malformed(), 1);
    }

    #[test]
    fn wheels_and_twist_are_inverse() {
        let (l, r) = GEOMETRY.wheels(0.2, 0.5);
        let (v, w) = GEOMETRY.twist(l, r);
        assert!((v - 0.2).abs() < 1e-12 && (w - 0.5).abs() < 1e-12);
    }
}

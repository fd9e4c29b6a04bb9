//! WASM translators (the `translator` world): the guest in
//! guest-components/rust/translator-ascii speaks the same ASCII protocol as
//! the built-in profile, byte for byte, and can drive a serial link.

use std::io::Read;
use std::time::{Duration, Instant};

use serialport::SerialPort;
use subsume::contract::control::ControlCommand;
use subsume::contract::{Param, Value};
use subsume::robot::protocol::{Feedback, Profile};
use subsume::robot::serial::{LinkSettings, SerialLink};
use subsume::robot::translator::{DriveGeometry, ProfileTranslator, TranslateError, Translator};
use subsume::runtime::Component;
use subsume::sandbox::{GuestLimits, Sandbox, WasmTranslator};

use crate::support::{self, sandbox};

const GEOMETRY: DriveGeometry = DriveGeometry { wheel_base: 0.3, max_wheel_speed: 0.5 };

fn wasm_translator(sandbox: &Sandbox) -> WasmTranslator {
    let bytes = std::fs::read(support::guest("translator-ascii")).unwrap();
    let artifact = sandbox.load_translator(&bytes).unwrap();
    let params = vec![
        Param { name: "wheel-base".into(), value: "0.3".into() },
        Param { name: "max-wheel-speed".into(), value: "0.5".into() },
    ];
    let limits = GuestLimits { memory_bytes: 16 << 20, budget: Duration::from_millis(20), ..GuestLimits::default() };
    sandbox.instantiate_translator(&artifact, "motors", &limits, &params).unwrap()
}

fn encode(translator: &mut dyn Translator, command: &str) -> Result<Vec<u8>, TranslateError> {
    let command: ControlCommand = command.parse().unwrap();
    let mut out = Vec::new();
    translator.encode(&command, &mut out).map(|()| out)
}

#[test]
fn the_wasm_translator_writes_the_same_bytes_as_the_builtin_profile() {
    let sandbox = sandbox();
    let mut wasm = wasm_translator(&sandbox);
    let mut builtin = ProfileTranslator::new(Profile::Ascii, GEOMETRY);
    let golden: [(&str, &[u8]); 5] = [
        ("STOP", b"S\n"),
        ("VEL 0.2 0", b"M 200 200\n"),
        ("VEL 0 1", b"M -150 150\n"),
        ("VEL 1 2", b"M 269 500\n"),
        ("VEL -0.1 -0.5", b"M -25 -175\n"),
    ];
    for (command, bytes) in golden {
        assert_eq!(encode(&mut wasm, command).as_deref(), Ok(bytes), "{command}");
        assert_eq!(encode(&mut builtin, command).as_deref(), Ok(bytes), "{command}");
    }
    assert!(matches!(encode(&mut wasm, "GOTO 1 2"), Err(TranslateError::Refused(m)) if m.contains("STOP and VEL")));
}

#[test]
fn the_wasm_translator_decodes_feedback_like_the_builtin_profile() {
    let sandbox = sandbox();
    let mut wasm = wasm_translator(&sandbox);
    let mut builtin = ProfileTranslator::new(Profile::Ascii, GEOMETRY);
    let bytes = b"O 1500 -2000 813\nbad line\nR 500 4000\nB 1\nP 12250\nF m1  over current\n";
    for translator in [&mut wasm as &mut dyn Translator, &mut builtin] {
        let mut out = Vec::new();
        // Split mid-line: partial lines wait for the rest.
        translator.decode(&bytes[..10], &mut out).unwrap();
        translator.decode(&bytes[10..], &mut out).unwrap();
        assert_eq!(
            out,
            vec![
                Feedback::Odometry { x: 1.5, y: -2.0, heading: 0.813 },
                Feedback::Ranges(vec![0.5, 4.0]),
                Feedback::Bumper(true),
                Feedback::Battery(12.25),
                Feedback::Fault(Some("m1 over current".into())),
            ]
        );
        assert_eq!(translator.malformed(), 1);
        // The controller's fault clears: `F` alone (the WASM translator
        // tells it through `host.report` during `decode`).
        let mut out = Vec::new();
        translator.decode(b"F\n", &mut out).unwrap();
        assert_eq!(out, vec![Feedback::Fault(None)]);
    }
}

#[test]
fn a_component_of_another_world_is_not_a_translator() {
    let sandbox = sandbox();
    let bytes = std::fs::read(support::guest("avoider")).unwrap();
    let err = sandbox.load_translator(&bytes).err().map(|e| e.to_string()).unwrap_or_default();
    assert!(err.starts_with("does not fit the subsume:robot/translator world"), "{err}");
}

#[test]
fn a_serial_link_drives_the_pty_through_the_wasm_translator() {
    let sandbox = sandbox();
    let (mut master, _slave, device) = support::pty();
    master.set_timeout(Duration::from_millis(20)).unwrap();
    let settings = LinkSettings {
        device,
        baud: 115_200,
        min_interval_ns: 1,
        watchdog_ns: 10_000_000_000,
        refresh_ns: 10_000_000_000,
    };
    let mut link = SerialLink::start("motors", settings, Box::new(wasm_translator(&sandbox))).unwrap();
    let deadline = Instant::now() + Duration::from_secs(5);
    while !link.status().connected {
        assert!(Instant::now() < deadline, "never connected");
        std::thread::sleep(Duration::from_millis(5));
    }
    link.on_input(0, &Value::Command("VEL 0.3 0.5".into()), 0, 0, &mut Vec::new()).unwrap();
    let mut received = Vec::new();
    let mut buffer = [0u8; 64];
    while !received.ends_with(b"\n") {
        assert!(Instant::now() < deadline, "no bytes: {received:?}");
        if let Ok(n) = master.read(&mut buffer) {
            received.extend_from_slice(&buffer[..n]);
        }
    }
    assert_eq!(received, b"M 225 375\n");
}

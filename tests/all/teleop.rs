//! Teleoperation end to end: the built binary with a `builtin:teleop`,
//! operators over real loopback TCP and WebSocket connections.

use std::io::Read;
use std::net::TcpStream;
use std::time::{Duration, Instant};

use serde_json::Value as Json;

use crate::support::{self, Operator, PASS_ENVELOPE, read_report, subsume, wait_for_exit, with_guests};

const TOKEN: &str = "alice-token-0123456789";
const BOB_TOKEN: &str = "bob-token-0123456789";

/// A running host and the address of its teleoperation port.
struct Host {
    process: support::HostProcess,
    address: String,
    websocket: Option<String>,
    _dir: tempfile::TempDir,
    report: std::path::PathBuf,
}

/// Starts `subsume run` on a robot file whose body is `components` (inside
/// the control platform), with `teleop_params` on the teleop component.
fn start(teleop_params: &str, components: &str, duration_s: u32) -> Host {
    support::guest_dir();
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("operators"), format!("# test operators\nalice {TOKEN}\nbob {BOB_TOKEN}\n"))
        .unwrap();
    let xml = format!(
        r#"<robot name="net">
  <platform name="network">
    <component name="teleop" source="builtin:teleop" rate="100" timeout="300ms">
      <param name="listen" value="127.0.0.1:0"/>
      <param name="operators" value="operators"/>
      {teleop_params}
    </component>
  </platform>
  <platform name="control">
    {components}
  </platform>
</robot>"#
    );
    let robot = dir.path().join("robot.xml");
    std::fs::write(&robot, with_guests(&xml)).unwrap();
    let report = dir.path().join("report.json");
    let mut command = subsume();
    command.args(["run", robot.to_str().unwrap()]);
    command.args(["--duration", &duration_s.to_string(), "--report", report.to_str().unwrap()]);
    let process = support::HostProcess::spawn(command);
    let address = process.word_after("teleoperation on tcp ", Duration::from_secs(30));
    let websocket = teleop_params.contains("websocket").then(|| {
        let url = process.word_after("teleoperation websocket on ws://", Duration::from_secs(30));
        url.split('/').next().unwrap_or_default().to_string()
    });
    Host { process, address, websocket, _dir: dir, report }
}

/// An operator connected to `host`'s teleoperation port (greeted as the
/// robot `net`).
fn connect(host: &Host) -> Operator {
    let (operator, hello) = Operator::connect_to(&host.address);
    assert!(hello.starts_with("HELLO subsume ") && hello.ends_with(" robot=net"), "{hello}");
    operator
}

fn allowed(rtt_line: &str) -> &str {
    rtt_line.split(" ALLOWED ").nth(1).unwrap_or("")
}

const SINK: &str = r#"<component name="arbiter" source="builtin:arbiter" rate="50"/>
    <component name="sink" source="builtin:log" rate="0"/>
    <connect from="teleop.cmd" to="arbiter.commands"/>
    <connect from="arbiter.cmd" to="sink.in"/>"#;

#[test]
fn every_line_gets_an_answer_and_the_connection_stays_usable() {
    let host = start("", SINK, 30);
    let mut alice = connect(&host);
    #[rustfmt::skip]
    let before_login = [
        ("CMD 1 0 STOP", "ERR authenticate first: AUTH <name> <token>"),
        ("MODE direct", "ERR authenticate first: AUTH <name> <token>"),
        ("FLY", "ERR unknown message 'FLY': expected AUTH, MODE, CMD, PONG, ESTOP, RELEASE or QUIT"),
        ("AUTH alice", "ERR AUTH takes a name and a token: AUTH <name> <token>"),
        ("AUTH alice not-the-token-at-all", "ERR authentication failed"),
    ];
    for (line, answer) in before_login {
        alice.send(line);
        assert_eq!(alice.reply(), answer, "{line}");
    }
    let rtt = alice.login("alice", TOKEN);
    assert_eq!(allowed(&rtt), "direct,shared,supervisory", "{rtt}");
    let long = format!("CMD 1 0 {}", "x".repeat(600));
    #[rustfmt::skip]
    let after_login = [
        ("CMD 1 0 VEL 0.1 0", "ERR ask for a control mode first: MODE direct|shared|supervisory".to_string()),
        ("MODE warp", "ERR unknown mode 'warp': expected direct, shared or supervisory".to_string()),
        ("AUTH alice x", "ERR already authenticated as alice".to_string()),
        ("PONG 999", "ERR no PING with nonce 999 is outstanding".to_string()),
        (long.as_str(), "ERR line longer than 512 bytes: ignored".to_string()),
    ];
    for (line, answer) in after_login {
        alice.send(line);
        assert_eq!(alice.reply(), answer, "{}", &line[..line.len().min(40)]);
    }
    alice.send("MODE direct");
    let granted = alice.reply();
    assert!(granted.starts_with("MODE direct granted: rtt "), "{granted}");
    for (line, answer) in [
        ("CMD 1 0 FLY 2", "ERR bad control string: column 1: unknown command 'FLY': expected STOP, VEL or GOTO"),
        ("CMD x 0 STOP", "ERR sequence number 'x' is not a whole number"),
    ] {
        alice.send(line);
        assert_eq!(alice.reply(), answer, "{line}");
    }
    alice.send("CMD 5 100 VEL 0.1 0");
    alice.send("CMD 5 100 VEL 0.1 0");
    alice.send("CMD 4 90 VEL 0.1 0");
    assert_eq!(alice.reply(), "DROP 5 duplicate or out of order");
    assert_eq!(alice.reply(), "DROP 4 duplicate or out of order");

    // A second operator can log in and watch, but not take control.
    let mut bob = connect(&host);
    bob.login("bob", BOB_TOKEN);
    bob.send("MODE shared");
    assert_eq!(bob.reply(), "ERR control is held by alice");
    alice.send("QUIT");
    assert_eq!(alice.reply(), "OK bye");
    let mut rest = String::new();
    assert_eq!(alice.reader.read_to_string(&mut rest).unwrap_or(0), 0, "the connection closes after QUIT");
    // Once alice has left, bob may take control.
    let deadline = Instant::now() + Duration::from_secs(5);
    loop {
        bob.send("MODE shared");
        let answer = bob.reply();
        if answer.starts_with("MODE shared granted") {
            break;
        }
        assert!(Instant::now() < deadline, "{answer}");
        std::thread::sleep(Duration::from_millis(50));
    }
}

#[test]
fn three_failed_logins_close_the_connection() {
    let host = start("", SINK, 30);
    let mut mallory = connect(&host);
    for _ in 0..2 {
        mallory.send("AUTH alice guess-guess-guess");
        assert_eq!(mallory.reply(), "ERR authentication failed");
    }
    mallory.send("AUTH alice guess-guess-guess");
    assert_eq!(mallory.reply(), "ERR authentication failed");
    assert_eq!(mallory.reply(), "ERR too many failed attempts: closing");
    let mut rest = String::new();
    assert_eq!(mallory.reader.read_to_string(&mut rest).unwrap_or(0), 0);
}

#[test]
fn the_link_quality_decides_the_modes_and_a_worse_link_downgrades_the_operator() {
    let host = start(r#"<param name="probe-period" value="0.5"/>"#, SINK, 60);
    let mut alice = connect(&host);
    alice.pong_delay = Duration::from_millis(50);
    let rtt = alice.login("alice", TOKEN);
    assert_eq!(allowed(&rtt), "direct,shared,supervisory", "{rtt}");
    alice.send("MODE direct");
    assert!(alice.reply().starts_with("MODE direct granted"));

    // The link gets worse: about 150 ms.
    alice.pong_delay = Duration::from_millis(150);
    let rtt = alice.reply();
    let rtt = if allowed(&rtt) == "direct,shared,supervisory" { alice.reply() } else { rtt };
    assert_eq!(allowed(&rtt), "shared,supervisory", "{rtt}");
    let notice = alice.reply();
    assert!(notice.starts_with("MODE shared downgraded from direct: rtt 15"), "{notice}");
    assert!(notice.ends_with("allows shared, supervisory"), "{notice}");
    alice.send("MODE direct");
    let refused = alice.reply();
    assert!(refused.starts_with("ERR mode direct is not allowed: measured rtt 15"), "{refused}");
    assert!(refused.ends_with("allows shared, supervisory"), "{refused}");

    // And worse: about 400 ms.
    alice.pong_delay = Duration::from_millis(400);
    let rtt = alice.reply();
    let rtt = if allowed(&rtt) == "shared,supervisory" { alice.reply() } else { rtt };
    assert_eq!(allowed(&rtt), "supervisory", "{rtt}");
    let notice = alice.reply();
    assert!(notice.starts_with("MODE supervisory downgraded from shared: rtt 40"), "{notice}");
    alice.send("QUIT");
    assert_eq!(alice.reply(), "OK bye");
}

#[test]
fn an_operator_drives_the_simulated_robot_over_tcp() {
    let world = support::repo_root().join("config/worlds/demo.world");
    let components = format!(
        r#"<component name="sim" source="builtin:sim"><param name="world" value="{}"/></component>
    <component name="motors" source="builtin:serial" rate="100"><param name="device" value="sim:sim"/></component>
    <component name="arbiter" source="builtin:arbiter" rate="50"/>
    <connect from="teleop.cmd" to="arbiter.commands"/>
    {PASS_ENVELOPE}
    <connect from="arbiter.cmd" to="envelope.cmd"/>
    <connect from="envelope.cmd" to="motors.cmd"/>"#,
        world.display()
    );
    let mut host = start("", &components, 6);
    let mut alice = connect(&host);
    alice.login("alice", TOKEN);
    alice.send("MODE direct");
    assert!(alice.reply().starts_with("MODE direct granted"));
    // Drive forward for 2 s, one command every 50 ms.
    for _ in 0..40 {
        alice.command("VEL 0.3 0");
        std::thread::sleep(Duration::from_millis(50));
    }
    alice.send("QUIT");
    wait_for_exit(&mut host.process.child, Duration::from_secs(20));
    let report = read_report(&host.report);
    let travelled = report["sim"]["distance_travelled_m"].as_f64().unwrap();
    assert!((0.4..0.9).contains(&travelled), "{}", report["sim"]);
    let session = &report["teleop"]["sessions"][0];
    assert_eq!(session["operator"], "alice");
    assert_eq!(session["mode_changes"][0]["to"], "direct");
    assert!(session["rtt_ms"].as_f64().unwrap() < 50.0);
    assert!(session["disconnected_at_s"].is_number());
    let commands = &report["teleop"]["commands"];
    assert_eq!(commands["received"], 40, "{commands}");
    assert!(commands["released"].as_u64().unwrap() >= 35, "{commands}");
    assert_eq!((commands["dropped_stale"].as_u64(), commands["dropped_duplicate"].as_u64()), (Some(0), Some(0)));
    assert!(report["arbiter"]["held_s"][0][1].as_f64().unwrap() > 1.5, "{}", report["arbiter"]);
}

/// Operators connecting over and over, several at once, each taking
/// control in turn for one command: the report lists every session still
/// open and only the newest ended ones (a peer connecting in a loop must
/// not grow the host without bound), counts the others, and loses none of
/// their commands from the totals.
#[test]
fn sessions_past_the_listing_bound_are_counted_and_their_commands_kept() {
    use subsume::teleop::MAX_ENDED_SESSIONS_LISTED;
    let (threads, each) = (4, MAX_ENDED_SESSIONS_LISTED / 4 + 3);
    let total = threads * each;
    let run_s = 25;
    let host = start(r#"<param name="max-operators" value="8"/>"#, SINK, run_s);
    let started = Instant::now();
    let workers: Vec<_> = (0..threads)
        .map(|t| {
            let address = host.address.clone();
            std::thread::spawn(move || {
                for i in 0..each {
                    let (mut operator, hello) = Operator::connect_to(&address);
                    assert!(hello.starts_with("HELLO "), "{hello}");
                    let (name, token) = if (t + i) % 2 == 0 { ("alice", TOKEN) } else { ("bob", BOB_TOKEN) };
                    operator.login(name, token);
                    // Control is held by one session at a time: wait a turn.
                    loop {
                        operator.send("MODE supervisory");
                        let reply = operator.reply();
                        if reply.starts_with("MODE supervisory") {
                            break;
                        }
                        assert!(reply.starts_with("ERR control is held by"), "{reply}");
                        std::thread::sleep(Duration::from_millis(5));
                    }
                    operator.command("VEL 0.1 0");
                    operator.send("QUIT");
                    assert_eq!(operator.reply(), "OK bye");
                    // The host closes the connection after it closed the session.
                    let mut rest = String::new();
                    let _ = operator.reader.read_to_string(&mut rest);
                }
            })
        })
        .collect();
    for worker in workers {
        worker.join().unwrap();
    }
    // The report is written at the end of the run: the last session must
    // have ended well before it.
    assert!(
        started.elapsed() < Duration::from_secs(run_s as u64 - 5),
        "{total} sessions took {:?} of a {run_s} s run",
        started.elapsed()
    );
    let mut host = host;
    wait_for_exit(&mut host.process.child, Duration::from_secs(run_s as u64 + 20));
    let report = read_report(&host.report);
    let network = &report["teleop"];
    let sessions = network["sessions"].as_array().unwrap();
    assert_eq!(sessions.len(), MAX_ENDED_SESSIONS_LISTED, "{network}");
    assert!(sessions.iter().all(|s| s["disconnected_at_s"].is_number()), "{network}");
    assert!(sessions.iter().all(|s| s["commands"]["received"] == 1), "{network}");
    assert_eq!(network["earlier_sessions"], (total - MAX_ENDED_SESSIONS_LISTED) as u64, "{network}");
    assert_eq!(network["commands"]["received"], total as u64, "{network}");
}

/// Issue 34: from 127.0.0.2, 200 idle connections (each reopened when the
/// host closes it) and a loop reconnecting as fast as it can, for 30 s;
/// from 127.0.0.3 an operator connects, logs in and drives once a second.
/// Every attempt gets in within 1 s, every command is counted, and the
/// control loop keeps its rate.
#[test]
fn idle_connections_and_a_reconnect_loop_never_keep_an_operator_out() {
    use std::net::{IpAddr, SocketAddr};
    use subsume::teleop::MAX_UNAUTHENTICATED_PER_ADDRESS;
    let attack = Duration::from_secs(30);
    let run_s = 40;
    let host = start(r#"<param name="auth-timeout" value="5"/>"#, SINK, run_s);
    let target: SocketAddr = host.address.parse().unwrap();
    let attacker: IpAddr = "127.0.0.2".parse().unwrap();
    let operator_address: IpAddr = "127.0.0.3".parse().unwrap();
    let flood = support::flood::Flood::start(attacker, target, 200, b"", None);
    std::thread::sleep(Duration::from_secs(1));
    let started = Instant::now();
    let mut attempts = 0u32;
    let mut slowest = Duration::ZERO;
    while started.elapsed() + Duration::from_secs(1) < attack {
        let due = started + Duration::from_secs(u64::from(attempts));
        std::thread::sleep(due.saturating_duration_since(Instant::now()));
        let attempt = Instant::now();
        let stream = support::flood::connect_from(operator_address, target).unwrap();
        let (mut operator, hello) = Operator::over(stream);
        assert!(hello.starts_with("HELLO subsume "), "attempt {attempts}: {hello}");
        operator.send(&format!("AUTH alice {TOKEN}"));
        assert_eq!(operator.reply(), "OK authenticated as alice; measuring the round-trip time");
        let took = attempt.elapsed();
        assert!(took < Duration::from_secs(1), "attempt {attempts} took {took:?} to get in");
        slowest = slowest.max(took);
        assert!(operator.reply().starts_with("RTT "));
        operator.send("MODE direct");
        let granted = operator.reply();
        assert!(granted.starts_with("MODE direct granted"), "attempt {attempts}: {granted}");
        operator.command("VEL 0.1 0");
        operator.send("QUIT");
        assert_eq!(operator.reply(), "OK bye");
        attempts += 1;
    }
    let flood = flood.stop();
    eprintln!("{attempts} attempts, the slowest in {slowest:?}; the flood: {flood:?}");
    assert!(attempts >= 25, "{attempts} attempts");
    assert!(flood.connects > 10_000, "the flood never flooded: {flood:?}");
    let per_address = format!(
        "ERR busy: unauthenticated connections: {MAX_UNAUTHENTICATED_PER_ADDRESS} are open from 127.0.0.2 already"
    );
    assert!(flood.heard.contains(&per_address), "{flood:?}");
    assert!(flood.heard.contains("ERR no authentication in time: closing"), "{flood:?}");
    let mut host = host;
    wait_for_exit(&mut host.process.child, Duration::from_secs(run_s as u64 + 20));
    let report = read_report(&host.report);
    assert_eq!(report["teleop"]["commands"]["received"], u64::from(attempts), "{}", report["teleop"]);
    let teleop = report["components"].as_array().unwrap().iter().find(|c| c["name"] == "teleop").unwrap();
    support::kept_its_rate(&report, teleop, 100.0, 0.05, 0.0, "the network platform under the flood");
}

#[test]
fn when_the_operator_disconnects_stop_reaches_the_motors_within_the_timeout() {
    let (mut motors, _slave, device) = support::MotorRecorder::new();
    let components = format!(
        r#"<component name="motors" source="builtin:serial" rate="100"><param name="device" value="{device}"/></component>
    <component name="arbiter" source="builtin:arbiter" rate="50"/>
    <connect from="teleop.cmd" to="arbiter.commands"/>
    {PASS_ENVELOPE}
    <connect from="arbiter.cmd" to="envelope.cmd"/>
    <connect from="envelope.cmd" to="motors.cmd"/>"#
    );
    let host = start("", &components, 30);
    let mut alice = connect(&host);
    alice.login("alice", TOKEN);
    alice.send("MODE direct");
    assert!(alice.reply().starts_with("MODE direct granted"));
    for _ in 0..20 {
        alice.command("VEL 0.2 0");
        let until = Instant::now() + Duration::from_millis(50);
        motors.read_while(|| Instant::now() < until);
    }
    // The operator vanishes.
    drop(alice);
    let gone = Instant::now();
    motors.read_while(|| Instant::now() < gone + Duration::from_millis(800));
    let lines = motors.lines;
    assert!(lines.iter().any(|(_, l)| l == "M 200 200"), "the operator drove: {lines:?}");
    let stop = lines.iter().find(|(at, l)| *at > gone && l == "S").expect("STOP reached the motors");
    // The network source's timeout is 300 ms; the arbiter ticks at 50 Hz.
    assert!(stop.0.duration_since(gone) < Duration::from_millis(400), "STOP after {:?}", stop.0.duration_since(gone));
}

#[test]
fn the_same_protocol_works_over_websocket_as_json() {
    let host = start(r#"<param name="websocket" value="127.0.0.1:0"/>"#, SINK, 30);
    let url = format!("ws://{}/teleop", host.websocket.clone().unwrap_or_default());
    let (mut socket, _) = tungstenite::connect(url.as_str()).unwrap();
    let next = |socket: &mut tungstenite::WebSocket<tungstenite::stream::MaybeTlsStream<TcpStream>>| -> Json {
        loop {
            let message = socket.read().unwrap();
            if let tungstenite::Message::Text(text) = message {
                let json: Json = serde_json::from_str(text.as_str()).unwrap();
                if json["type"] == "ping" {
                    let pong = serde_json::json!({"type": "pong", "nonce": json["nonce"]}).to_string();
                    socket.send(tungstenite::Message::Text(pong.into())).unwrap();
                    continue;
                }
                return json;
            }
        }
    };
    let send = |socket: &mut tungstenite::WebSocket<tungstenite::stream::MaybeTlsStream<TcpStream>>, json: Json| {
        socket.send(tungstenite::Message::Text(json.to_string().into())).unwrap();
    };
    assert_eq!(next(&mut socket)["type"], "hello");
    send(&mut socket, serde_json::json!({"type": "cmd", "seq": 1, "time_ms": 0, "command": "STOP"}));
    assert_eq!(
        next(&mut socket),
        serde_json::json!({"type": "error", "message": "authenticate first: AUTH <name> <token>"})
    );
    send(&mut socket, serde_json::json!({"type": "auth", "name": "alice", "token": TOKEN}));
    assert_eq!(next(&mut socket)["type"], "ok");
    let rtt = next(&mut socket);
    assert_eq!(rtt["type"], "rtt");
    assert_eq!(rtt["allowed"], serde_json::json!(["direct", "shared", "supervisory"]));
    send(&mut socket, serde_json::json!({"type": "mode", "mode": "shared"}));
    let mode = next(&mut socket);
    assert_eq!((mode["type"].as_str(), mode["mode"].as_str()), (Some("mode"), Some("shared")), "{mode}");
    socket.send(tungstenite::Message::Text("{not json".into())).unwrap();
    assert!(next(&mut socket)["message"].as_str().unwrap().starts_with("not a JSON object"));
}

#[test]
fn the_keyboard_client_drives_from_a_real_terminal() {
    let mut host = start("", SINK, 8);
    // `script` gives the client a real pseudo-terminal; what we write to its
    // stdin arrives as key presses.
    let client = format!("{} teleop {} --name alice --token {TOKEN}", support::BIN, host.address);
    let mut terminal = support::Terminal::start(&client);
    // The client logs in, is measured and asks for the best mode.
    terminal.wait_for("mode direct");
    terminal.wait_for("rtt ");
    terminal.press(&b"\x1b[A".repeat(4)); // arrow up, 4 times: faster
    terminal.wait_for("vel +0.20");
    std::thread::sleep(Duration::from_millis(1500));
    terminal.press(b" "); // space: stop
    terminal.wait_for("vel +0.00");
    terminal.press(b"q");
    terminal.wait_for_quit();
    wait_for_exit(&mut host.process.child, Duration::from_secs(20));
    let report = read_report(&host.report);
    let session = &report["teleop"]["sessions"][0];
    assert_eq!(session["operator"], "alice", "{session}");
    assert_eq!(session["mode_changes"][0]["to"], "direct", "{session}");
    assert!(session["commands"]["released"].as_u64().unwrap() >= 10, "{session}");
    // It drove: the network source held control for most of that time.
    let held = report["arbiter"]["held_s"][0][1].as_f64().unwrap();
    assert!(held > 1.0, "{}", report["arbiter"]);
}

/// Sends `command` every 50 ms for `for_ms`, reading what arrives meanwhile.
fn drive(operator: &mut Operator, command: &str, for_ms: u64) {
    for _ in 0..for_ms / 50 {
        operator.command(command);
        std::thread::sleep(Duration::from_millis(50));
    }
}

#[test]
fn the_readme_drive_works_on_the_demo_and_the_operator_is_told_who_holds_control() {
    // README: run the demo (config/demo.xml), then drive it as operator
    // `demo` with the token from config/demo-operators, in direct mode,
    // while the planner (priority 1) drives toward its goal.
    support::guest_dir();
    let dir = tempfile::tempdir().unwrap();
    let report = dir.path().join("report.json");
    let mut command = subsume();
    command.args(["run", "config/demo.xml"]);
    command.args(["--param", "teleop.listen=127.0.0.1:0", "--param", "teleop.websocket="]);
    command.args(["--duration", "20", "--report", report.to_str().unwrap()]);
    let mut host = support::HostProcess::spawn(command);
    let address = host.word_after("teleoperation on tcp ", Duration::from_secs(60));
    let (mut demo, hello) = Operator::connect_to(&address);
    assert!(hello.ends_with(" robot=demo"), "{hello}");
    let rtt = demo.login("demo", "demo-token-change-me");
    assert!(allowed(&rtt).contains("direct"), "{rtt}");
    // Supervisory (priority 0) is below the planner: the operator is told,
    // with the mode that would win.
    demo.send("MODE supervisory");
    assert!(demo.reply().starts_with("MODE supervisory granted"));
    drive(&mut demo, "VEL 0 0.6", 500);
    // (The avoider, priority 3, may hold instead if the robot is near a
    // wall by now: then no mode would win.)
    let suppressed = demo.await_control("CONTROL suppressed ");
    assert!(
        [
            "CONTROL suppressed planner 1 suppressed by planner (priority 1): direct or shared mode would win",
            "CONTROL suppressed avoid 3 suppressed by avoid (priority 3): no control mode outranks it"
        ]
        .contains(&suppressed.as_str()),
        "{suppressed}"
    );
    // Direct mode ties with the planner, and the operator wins the tie.
    demo.send("MODE direct");
    assert!(demo.reply().starts_with("MODE direct granted"));
    drive(&mut demo, "VEL 0 0.6", 3000);
    assert_eq!(demo.await_control("CONTROL held"), "CONTROL held your commands drive the robot");
    demo.send("QUIT");
    wait_for_exit(&mut host.child, Duration::from_secs(40));
    let report = read_report(&report);
    let held: f64 = report["arbiter"]["held_s"]
        .as_array()
        .unwrap()
        .iter()
        .find(|entry| entry[0] == "teleop")
        .and_then(|entry| entry[1].as_f64())
        .unwrap();
    assert!(held > 0.5, "the operator held control for {held} s: {}", report["arbiter"]);
}

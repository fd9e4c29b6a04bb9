//! Shared by every module of the integration tests (and included by the
//! benchmarks): where the repository is, the one way to run the `subsume`
//! binary, the guest components (built once per test process), hosts whose
//! log a test waits on, pseudo-terminals that play motor controllers, HTTP
//! to the portal, users and logins, operators on the line protocol, a
//! terminal client, test certificates, the browser, and readers of what the
//! host writes (reports, recordings).
//!
//! Every module's tests run in this one process, two at a time: what is
//! process-wide is made safe here. The guests are built once (two builds
//! at once would write the same files); pseudo-terminals are opened
//! close-on-exec, so a child process another test spawns never holds one
//! open; ports are free ones, folders fresh ones.

#![allow(dead_code, clippy::panic, clippy::unwrap_used, clippy::expect_used)]

use std::io::{BufRead, BufReader, Read, Write};
use std::net::TcpStream;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitStatus, Stdio};
use std::sync::OnceLock;
use std::time::{Duration, Instant};

use serde_json::Value as Json;

/// The built `subsume` binary.
pub const BIN: &str = env!("CARGO_BIN_EXE_subsume");

/// `--param`s that move the demo's operator ports (config/demo.xml listens
/// on fixed ones) to free ones, so runs of it can go on side by side.
pub const FREE_TELEOP_PORTS: [&str; 4] =
    ["--param", "teleop.listen=127.0.0.1:0", "--param", "teleop.websocket=127.0.0.1:0"];

/// The envelope (`envelope`, between the arbiter and the motors) of a robot
/// that checks what reaches its motors: it passes every command unchanged
/// (no sensors wired, limits far above what the tests send). The validator
/// requires an envelope in front of the motors.
pub const PASS_ENVELOPE: &str = r#"<component name="envelope" source="builtin:envelope" rate="20">
      <param name="max-speed" value="10"/><param name="max-reverse" value="10"/><param name="max-turn" value="20"/>
      <param name="max-accel" value="100"/><param name="max-turn-accel" value="100"/>
    </component>"#;

#[path = "support/flood.rs"]
pub mod flood;

/// The repository root.
pub fn repo_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).parent().map_or_else(|| PathBuf::from(".."), Path::to_path_buf)
}

/// The folder holding the built guest components (`NAME.wasm`), building
/// them first if this process has not yet done so.
pub fn guest_dir() -> PathBuf {
    static BUILT: OnceLock<Result<PathBuf, String>> = OnceLock::new();
    let built = BUILT.get_or_init(|| {
        let dir = repo_root().join("guest-components/rust");
        let cargo = std::env::var_os("CARGO").unwrap_or_else(|| "cargo".into());
        let output = Command::new(cargo)
            .args(["build", "--release", "--quiet"])
            .current_dir(&dir)
            .env_remove("CARGO_TARGET_DIR")
            .output()
            .map_err(|e| format!("cannot run cargo to build the guests: {e}"))?;
        if !output.status.success() {
            return Err(format!("building the guests failed:\n{}", String::from_utf8_lossy(&output.stderr)));
        }
        Ok(dir.join("target/wasm32-wasip2/release"))
    });
    match built {
        Ok(dir) => dir.clone(),
        Err(why) => panic!("{why}"),
    }
}

/// The built guest `name` (crate name with `-` as `_`).
pub fn guest(name: &str) -> PathBuf {
    guest_dir().join(format!("{}.wasm", name.replace('-', "_")))
}

/// Builds the C, Python and JavaScript guests (the avoiders and the test
/// components, `guest-components/build-all c python js`) once per test
/// process: every module that needs one waits for the same build, so no
/// two builds write the same files at once.
pub fn build_other_languages() {
    static BUILT: OnceLock<Result<(), String>> = OnceLock::new();
    let built = BUILT.get_or_init(|| {
        let output = Command::new(repo_root().join("guest-components/build-all"))
            .args(["c", "python", "js"])
            .env_remove("CARGO_TARGET_DIR")
            .output()
            .map_err(|e| format!("cannot run guest-components/build-all: {e}"))?;
        if !output.status.success() {
            return Err(format!(
                "guest-components/build-all c python js (scripts/setup installs the toolchains) failed:\n{}\n{}",
                text(&output.stdout),
                text(&output.stderr)
            ));
        }
        Ok(())
    });
    if let Err(why) = built {
        panic!("{why}");
    }
}

/// The tests' own Python (the virtualenv scripts/setup installs, with the
/// independent implementations the tests talk to).
pub fn python() -> PathBuf {
    let python = repo_root().join("tests/python/.venv/bin/python");
    assert!(python.is_file(), "{} is missing: run scripts/setup first", python.display());
    python
}

/// A compile cache shared by the tests of this checkout.
pub fn cache_dir() -> PathBuf {
    repo_root().join("target/test-component-cache")
}

/// A sandbox (its own engine) on the shared compile cache, the guests built.
pub fn sandbox() -> subsume::sandbox::Sandbox {
    guest_dir();
    subsume::sandbox::Sandbox::new(Some(cache_dir())).unwrap_or_else(|e| panic!("{e}"))
}

/// `subsume`, run from the repository root with the shared compile cache;
/// see [`subsume_with_cache`].
pub fn subsume() -> Command {
    subsume_with_cache(&cache_dir())
}

/// `subsume` run from the repository root (the guests built) with the
/// compile cache `cache` (`--no-cache` after it turns the cache off), `RUST_LOG=info`,
/// `NO_COLOR=1`, and no web portal: `SUBSUME_HTTP=off`, because tests run
/// side by side and the portal's default port is a fixed one. A test that
/// wants the portal passes `--http 127.0.0.1:0`, which wins over the
/// environment. The caller adds the subcommand and the rest.
pub fn subsume_with_cache(cache: &Path) -> Command {
    // Robot files name the built guests (config/demo.xml among them).
    guest_dir();
    let mut command = Command::new(BIN);
    command
        .current_dir(repo_root())
        .arg("--cache-dir")
        .arg(cache)
        .env("RUST_LOG", "info")
        .env("NO_COLOR", "1")
        .env("SUBSUME_HTTP", "off");
    command
}

/// Bytes as text (lossy).
pub fn text(bytes: &[u8]) -> String {
    String::from_utf8_lossy(bytes).into_owned()
}

/// The JSON run report at `path`.
pub fn read_report(path: &Path) -> Json {
    let bytes = std::fs::read(path).unwrap_or_else(|e| panic!("no report at {}: {e}", path.display()));
    serde_json::from_slice(&bytes).unwrap_or_else(|e| panic!("the report {} is not JSON: {e}", path.display()))
}

/// Component `name`'s entry in a run report.
pub fn component<'a>(report: &'a Json, name: &str) -> &'a Json {
    report["components"]
        .as_array()
        .unwrap()
        .iter()
        .find(|c| c["name"] == name)
        .unwrap_or_else(|| panic!("no component '{name}' in the report"))
}

/// `xml` with every `GUEST(name)` replaced by the path of the built guest.
pub fn with_guests(xml: &str) -> String {
    let mut out = String::new();
    let mut rest = xml;
    while let Some(at) = rest.find("GUEST(") {
        let name_end = rest[at..].find(')').map(|end| at + end).unwrap_or_else(|| panic!("unclosed GUEST( in {xml}"));
        out.push_str(&rest[..at]);
        out.push_str(&guest(&rest[at + "GUEST(".len()..name_end]).display().to_string());
        rest = &rest[name_end + 1..];
    }
    out.push_str(rest);
    out
}

/// Writes `dir/robot.xml` from `body` with its `GUEST(name)` placeholders
/// naming the built guests; returns its path.
pub fn robot_file(dir: &Path, body: &str) -> PathBuf {
    let path = dir.join("robot.xml");
    std::fs::write(&path, with_guests(body)).unwrap();
    path
}

/// A TCP port free on loopback when asked.
pub fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port()
}

/// Waits up to `limit` for `child` to exit; kills it and panics if it
/// does not.
pub fn wait_for_exit(child: &mut Child, limit: Duration) -> ExitStatus {
    let deadline = Instant::now() + limit;
    loop {
        if let Some(status) = child.try_wait().unwrap() {
            return status;
        }
        if Instant::now() > deadline {
            let _ = child.kill();
            panic!("the process did not exit within {limit:?}");
        }
        std::thread::sleep(Duration::from_millis(20));
    }
}

/// Sends `signal` (`INT`, `TERM`, `KILL`, ...) to process `pid` with kill(1).
pub fn signal(pid: u32, signal: &str) {
    let sent = Command::new("kill").arg(format!("-{signal}")).arg(pid.to_string()).status().unwrap();
    assert!(sent.success(), "kill -{signal} {pid}");
}

/// A pseudo-terminal: its master end (what a test plays: the motor
/// controller), its slave end (held open, so the device stays while the
/// host is not connected) and the slave's path (the device the host opens).
///
/// Both ends are opened close-on-exec from the start: this process runs
/// every module's tests, and a child that another test spawns must not
/// inherit an end. It would hold the terminal open after the test closed
/// it, and the host on the other end would never see its controller go.
pub fn pty() -> (serialport::TTYPort, std::fs::File, PathBuf) {
    use std::os::fd::{FromRawFd, IntoRawFd, OwnedFd};
    use std::os::unix::fs::OpenOptionsExt;
    // SAFETY: posix_openpt's descriptor is owned by an `OwnedFd` at once;
    // the other calls get that open descriptor and a buffer of the stated
    // length, which ptsname_r fills with a NUL-terminated name.
    let (master, path) = unsafe {
        let fd = libc::posix_openpt(libc::O_RDWR | libc::O_NOCTTY | libc::O_CLOEXEC);
        assert!(fd >= 0, "no pseudo-terminal: {}", std::io::Error::last_os_error());
        let master = OwnedFd::from_raw_fd(fd);
        assert!(libc::grantpt(fd) == 0 && libc::unlockpt(fd) == 0, "{}", std::io::Error::last_os_error());
        let mut name = [0 as libc::c_char; 128];
        assert_eq!(libc::ptsname_r(fd, name.as_mut_ptr(), name.len()), 0, "no name for the pseudo-terminal");
        (master, PathBuf::from(std::ffi::CStr::from_ptr(name.as_ptr()).to_string_lossy().into_owned()))
    };
    // std opens every file close-on-exec.
    let slave = std::fs::OpenOptions::new()
        .read(true)
        .write(true)
        .custom_flags(libc::O_NOCTTY)
        .open(&path)
        .unwrap_or_else(|e| panic!("cannot open {}: {e}", path.display()));
    // SAFETY: `slave` and `master` are open descriptors for the whole block;
    // `termios` is filled by tcgetattr before it is read; from_raw_fd takes
    // the master's descriptor over from the `OwnedFd` that let it go.
    let master = unsafe {
        use std::os::fd::AsRawFd;
        // Raw both ways until the host sets its own mode (raw too).
        let mut termios: libc::termios = std::mem::zeroed();
        assert_eq!(libc::tcgetattr(slave.as_raw_fd(), &mut termios), 0);
        libc::cfmakeraw(&mut termios);
        assert_eq!(libc::tcsetattr(slave.as_raw_fd(), libc::TCSANOW, &termios), 0);
        let fd = master.into_raw_fd();
        let port = serialport::TTYPort::from_raw_fd(fd);
        // from_raw_fd locks the descriptor as a serial port of its own;
        // the master is only read and written here.
        libc::flock(fd, libc::LOCK_UN);
        libc::ioctl(fd, libc::TIOCNXCL);
        port
    };
    (master, slave, path)
}

/// The far end of a pseudo-terminal playing a motor controller: records
/// every line the host writes, with the time it arrived, and every byte.
pub struct MotorRecorder {
    master: serialport::TTYPort,
    pending: String,
    /// Each complete line and when it was read.
    pub lines: Vec<(Instant, String)>,
    /// Every byte read, in order (binary protocols have no lines).
    pub bytes: Vec<u8>,
    /// When the last read returned, and the longest time between two reads
    /// returning: a line's time is late by at most that (a read waits at
    /// most [`MotorRecorder::READ_TIMEOUT`], so more means this thread
    /// waited for a CPU).
    last_read: Option<Instant>,
    pub max_read_gap: Duration,
}

impl MotorRecorder {
    /// A new pseudo-terminal ([`pty`]); the host opens the returned device
    /// path. Keep the returned file (the slave end) for as long as the
    /// device must stay.
    pub fn new() -> (MotorRecorder, std::fs::File, String) {
        use serialport::SerialPort;
        let (mut master, slave, path) = pty();
        master.set_timeout(MotorRecorder::READ_TIMEOUT).unwrap();
        let recorder = MotorRecorder {
            master,
            pending: String::new(),
            lines: Vec::new(),
            bytes: Vec::new(),
            last_read: None,
            max_read_gap: Duration::ZERO,
        };
        (recorder, slave, path.display().to_string())
    }

    /// The longest a read waits for bytes.
    pub const READ_TIMEOUT: Duration = Duration::from_millis(10);

    /// Reads what has arrived (waiting at most [`Self::READ_TIMEOUT`]).
    pub fn read(&mut self) {
        let mut buffer = [0u8; 256];
        let read = self.master.read(&mut buffer);
        let now = Instant::now();
        if let Some(last) = self.last_read.replace(now) {
            self.max_read_gap = self.max_read_gap.max(now - last);
        }
        if let Ok(n) = read {
            self.bytes.extend_from_slice(&buffer[..n]);
            self.pending.push_str(&String::from_utf8_lossy(&buffer[..n]));
            while let Some(end) = self.pending.find('\n') {
                self.lines.push((now, self.pending[..end].to_string()));
                self.pending.drain(..=end);
            }
        }
    }

    /// Writes `bytes` to the host, as the controller would (feedback).
    pub fn write(&mut self, bytes: &[u8]) {
        let _ = self.master.write_all(bytes);
    }

    /// Reads while `going` says so.
    pub fn read_while(&mut self, mut going: impl FnMut() -> bool) {
        while going() {
            self.read();
        }
    }
}

/// A pseudo-terminal to hand a child as its standard output or error (a
/// person's terminal, as `isatty` sees it): what the child writes there is
/// read from the master end. Both ends are [`pty`]'s, close-on-exec.
pub struct Pty {
    master: serialport::TTYPort,
    slave: std::fs::File,
    /// Everything read so far.
    pub text: String,
}

impl Pty {
    pub fn new() -> Pty {
        use serialport::SerialPort;
        let (mut master, slave, _) = pty();
        let _ = master.set_timeout(Duration::from_millis(50));
        Pty { master, slave, text: String::new() }
    }

    /// The terminal's end for the child (stdout or stderr).
    pub fn stdio(&self) -> Stdio {
        Stdio::from(self.slave.try_clone().unwrap())
    }

    /// Reads until `done` holds for the text read so far, for at most
    /// `timeout`; whether it held.
    pub fn read_until(&mut self, timeout: Duration, done: impl Fn(&str) -> bool) -> bool {
        let deadline = Instant::now() + timeout;
        let mut buffer = [0u8; 4096];
        while !done(&self.text) {
            if Instant::now() >= deadline {
                return false;
            }
            if let Ok(n) = Read::read(&mut self.master, &mut buffer) {
                self.text.push_str(&String::from_utf8_lossy(&buffer[..n]));
            }
        }
        true
    }
}

/// A running host whose stderr a thread reads into a log, so a test can
/// wait for what the host announces (its addresses) and show the whole log
/// when something is missing. Dropping it kills the host.
pub struct HostProcess {
    pub child: Child,
    log: std::sync::Arc<(std::sync::Mutex<Vec<String>>, std::sync::Condvar)>,
}

impl HostProcess {
    /// Spawns `command` (stdout discarded, stderr read).
    pub fn spawn(command: Command) -> HostProcess {
        HostProcess::spawn_with_stdout(command, Stdio::null())
    }

    /// Spawns `command` with this stdout (a pipe, a terminal), stderr read.
    pub fn spawn_with_stdout(mut command: Command, stdout: Stdio) -> HostProcess {
        let mut child = command
            .stdout(stdout)
            .stderr(Stdio::piped())
            .spawn()
            .unwrap_or_else(|e| panic!("cannot start the host: {e}"));
        let stderr = child.stderr.take().unwrap_or_else(|| panic!("no stderr pipe"));
        let log = std::sync::Arc::new((std::sync::Mutex::new(Vec::new()), std::sync::Condvar::new()));
        let writer = log.clone();
        std::thread::spawn(move || {
            for line in BufReader::new(stderr).lines().map_while(Result::ok) {
                let (lines, grew) = &*writer;
                lines.lock().unwrap_or_else(|e| e.into_inner()).push(line);
                grew.notify_all();
            }
        });
        HostProcess { child, log }
    }

    /// Waits up to `timeout` for a log line holding `marker` and returns the
    /// word after it (up to whitespace); panics with the log if none came.
    pub fn word_after(&self, marker: &str, timeout: Duration) -> String {
        let deadline = Instant::now() + timeout;
        let (lines, grew) = &*self.log;
        let mut lines = lines.lock().unwrap_or_else(|e| e.into_inner());
        loop {
            let found = lines.iter().find_map(|line| line.split_once(marker).map(|(_, rest)| rest.to_string()));
            if let Some(rest) = found {
                return rest.split_whitespace().next().unwrap_or_default().to_string();
            }
            let now = Instant::now();
            if now >= deadline {
                panic!("the host never said '{marker}':\n{}", lines.join("\n"));
            }
            lines = grew.wait_timeout(lines, deadline - now).unwrap_or_else(|e| e.into_inner()).0;
        }
    }

    /// The log lines from the `from`th on, up to and including the first
    /// that holds `what`; waits up to `timeout` for it, and panics with the
    /// log if it did not come.
    pub fn lines_until(&self, from: usize, what: &str, timeout: Duration) -> Vec<String> {
        let deadline = Instant::now() + timeout;
        let (lines, grew) = &*self.log;
        let mut lines = lines.lock().unwrap_or_else(|e| e.into_inner());
        loop {
            if let Some(at) = lines.iter().skip(from).position(|line| line.contains(what)) {
                return lines[from..=from + at].to_vec();
            }
            let now = Instant::now();
            if now >= deadline {
                panic!("no line with '{what}' within {timeout:?}:\n{}", lines[from.min(lines.len())..].join("\n"));
            }
            lines = grew.wait_timeout(lines, deadline - now).unwrap_or_else(|e| e.into_inner()).0;
        }
    }

    /// The address (`HOST:PORT`) the host announced after `marker`, as in
    /// `portal on http://127.0.0.1:8080/`; waits up to `timeout`.
    pub fn address_after(&self, marker: &str, timeout: Duration) -> String {
        self.word_after(marker, timeout).split('/').next().unwrap_or_default().to_string()
    }

    /// The address of the portal (plain HTTP) once it listens.
    pub fn portal_address(&self) -> String {
        self.address_after("portal on http://", Duration::from_secs(120))
    }

    /// Every stderr line so far.
    pub fn log(&self) -> String {
        self.log.0.lock().unwrap_or_else(|e| e.into_inner()).join("\n")
    }

    /// The host's child processes as the kernel sees them (state, CPU
    /// ticks, where each sleeps, its command line), and the last lines of
    /// the log beside a child's `--report` (a preflight's `preflight.log`):
    /// what a test that waited in vain for a child should print.
    pub fn children(&self) -> String {
        children_of(self.child.id())
    }
}

/// [`HostProcess::children`] for any process.
pub fn children_of(parent: u32) -> String {
    let mut out = String::new();
    let Ok(entries) = std::fs::read_dir("/proc") else { return "no /proc".into() };
    for entry in entries.flatten() {
        let Some(pid) = entry.file_name().to_str().and_then(|n| n.parse::<u32>().ok()) else { continue };
        let Ok(stat) = std::fs::read_to_string(format!("/proc/{pid}/stat")) else { continue };
        // After the command's closing parenthesis: state, ppid, ... utime
        // (the 14th field) and stime (15th).
        let Some((_, rest)) = stat.rsplit_once(") ") else { continue };
        let fields: Vec<&str> = rest.split_whitespace().collect();
        if fields.get(1).and_then(|p| p.parse::<u32>().ok()) != Some(parent) {
            continue;
        }
        let ticks = |i: usize| fields.get(i).and_then(|t| t.parse::<u64>().ok()).unwrap_or(0);
        let wchan = std::fs::read_to_string(format!("/proc/{pid}/wchan")).unwrap_or_default();
        let cmdline = std::fs::read(format!("/proc/{pid}/cmdline")).unwrap_or_default();
        let args: Vec<String> = cmdline
            .split(|b| *b == 0)
            .filter(|a| !a.is_empty())
            .map(|a| String::from_utf8_lossy(a).into_owned())
            .collect();
        out += &format!(
            "child {pid}: state {}, cpu ticks {} user {} system, waiting in '{wchan}', threads {}: {}\n",
            fields[0],
            ticks(11),
            ticks(12),
            fields.get(17).unwrap_or(&"?"),
            args.join(" ")
        );
        let report = args.iter().position(|a| a == "--report").and_then(|i| args.get(i + 1));
        if let Some(log) = report.and_then(|r| Path::new(r).parent()).map(|d| d.join("preflight.log")) {
            let text = std::fs::read_to_string(&log).unwrap_or_else(|e| format!("({e})"));
            let tail: Vec<&str> = text.lines().rev().take(20).collect();
            out += &format!("  {} (last lines):\n", log.display());
            for line in tail.iter().rev() {
                out += &format!("  | {line}\n");
            }
        }
    }
    if out.is_empty() { format!("process {parent} has no children") } else { out }
}

impl Drop for HostProcess {
    /// A test that ends early (or fails) leaves no host behind.
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// One HTTP/1.1 request to `address`: (status, body bytes).
pub fn http_bytes(address: &str, method: &str, path: &str, token: Option<&str>, body: &[u8]) -> (u16, Vec<u8>) {
    http_bytes_on(TcpStream::connect(address).unwrap(), address, method, path, token, body)
}

/// [`http_bytes`] on a connection the caller opened (e.g. from a chosen
/// source address).
pub fn http_bytes_on(
    mut stream: TcpStream,
    address: &str,
    method: &str,
    path: &str,
    token: Option<&str>,
    body: &[u8],
) -> (u16, Vec<u8>) {
    stream.set_read_timeout(Some(Duration::from_secs(60))).unwrap();
    let auth = token.map(|t| format!("Authorization: Bearer {t}\r\n")).unwrap_or_default();
    let head = format!(
        "{method} {path} HTTP/1.1\r\nHost: {address}\r\n{auth}Content-Length: {}\r\nConnection: close\r\n\r\n",
        body.len()
    );
    stream.write_all(head.as_bytes()).unwrap();
    // The server may answer (and close) before it read the whole body.
    let _ = stream.write_all(body);
    let mut response = Vec::new();
    let _ = stream.read_to_end(&mut response);
    let Some(split) = response.windows(4).position(|w| w == b"\r\n\r\n") else {
        return (0, response);
    };
    let status = text(&response[..split]).split(' ').nth(1).and_then(|s| s.parse().ok()).unwrap_or(0);
    (status, response[split + 4..].to_vec())
}

/// One HTTP/1.1 request to the portal at `address`: (status, JSON body,
/// or null when the body is not JSON).
pub fn http(address: &str, method: &str, path: &str, token: Option<&str>, body: &[u8]) -> (u16, Json) {
    let (status, body) = http_bytes(address, method, path, token, body);
    (status, serde_json::from_slice(&body).unwrap_or(Json::Null))
}

/// One request to the portal at `address` (`https://HOST:PORT`), trusting
/// only the authority in `ca` (PEM), with the command line's own client:
/// (status, JSON body, or null when the body is not JSON).
pub fn https(address: &str, ca: &Path, method: &str, path: &str, token: Option<&str>, body: &[u8]) -> (u16, Json) {
    use subsume::portal::client::{Connection, Login};
    let login = Login {
        host: address.to_string(),
        user: String::new(),
        password: String::new(),
        ca: Some(ca.to_path_buf()),
        allow_plain_http: false,
    };
    let connection = Connection::open(&login, Duration::from_secs(60)).unwrap();
    let answer = connection.send(method, path, token, "application/json", body).unwrap();
    let (status, json, _) = answer.read(64 << 20).unwrap();
    (status, json)
}

/// [`http`] on a connection the caller opened.
pub fn http_on(
    stream: TcpStream,
    address: &str,
    method: &str,
    path: &str,
    token: Option<&str>,
    body: &[u8],
) -> (u16, Json) {
    let (status, body) = http_bytes_on(stream, address, method, path, token, body);
    (status, serde_json::from_slice(&body).unwrap_or(Json::Null))
}

/// A test CA (`ca.pem`, `ca.key`) and a server certificate it signed for
/// localhost and 127.0.0.1 (`server.pem`, `server.key`; `chain.pem` holds
/// both certificates, as a full chain does), made in `dir` with the openssl
/// CLI (which scripts/setup installs).
pub fn make_test_pki(dir: &Path) {
    let openssl = |args: &[&str]| {
        let output = Command::new("openssl").current_dir(dir).args(args).output();
        let output = output.unwrap_or_else(|e| panic!("the openssl CLI is needed: {e}"));
        assert!(output.status.success(), "openssl {args:?}: {}", String::from_utf8_lossy(&output.stderr));
    };
    let ec = ["-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:P-256", "-nodes"];
    let mut ca = vec!["req", "-x509"];
    ca.extend(ec);
    ca.extend(["-keyout", "ca.key", "-out", "ca.pem", "-days", "2", "-subj", "/CN=subsume test CA"]);
    ca.extend(["-addext", "basicConstraints=critical,CA:TRUE", "-addext", "keyUsage=critical,keyCertSign,cRLSign"]);
    openssl(&ca);
    let mut csr = vec!["req"];
    csr.extend(ec);
    csr.extend(["-keyout", "server.key", "-out", "server.csr", "-subj", "/CN=localhost"]);
    openssl(&csr);
    let extensions = "subjectAltName=DNS:localhost,IP:127.0.0.1\nbasicConstraints=critical,CA:FALSE\n\
         keyUsage=critical,digitalSignature\nextendedKeyUsage=serverAuth\n\
         subjectKeyIdentifier=hash\nauthorityKeyIdentifier=keyid,issuer\n";
    std::fs::write(dir.join("server.ext"), extensions).unwrap_or_else(|e| panic!("cannot write server.ext: {e}"));
    let sign = ["x509", "-req", "-in", "server.csr", "-CA", "ca.pem", "-CAkey", "ca.key", "-CAcreateserial"];
    openssl(&[&sign[..], &["-out", "server.pem", "-days", "2", "-extfile", "server.ext"]].concat());
    let read = |name: &str| std::fs::read(dir.join(name)).unwrap_or_else(|e| panic!("cannot read {name}: {e}"));
    std::fs::write(dir.join("chain.pem"), [read("server.pem"), read("ca.pem")].concat())
        .unwrap_or_else(|e| panic!("cannot write chain.pem: {e}"));
}

/// The folder of the browser tests, checked to be set up.
pub fn browser_dir() -> PathBuf {
    let dir = repo_root().join("tests/browser");
    assert!(
        dir.join("node_modules/playwright-core").is_dir(),
        "run scripts/setup first: it installs playwright-core and chromium"
    );
    dir
}

/// Runs `tests/browser/SCRIPT ARGS..` (node with playwright-core driving
/// Debian's Chromium, both installed by scripts/setup) with `envs`, and
/// ARTIFACTS set to `artifacts`, where it saves its screenshots. Panics with
/// all it printed unless it succeeds; returns its stdout.
pub fn browser(script: &str, artifacts: &Path, envs: &[(&str, &str)], args: &[&dyn AsRef<std::ffi::OsStr>]) -> String {
    let output = Command::new("node")
        .current_dir(browser_dir())
        .env("ARTIFACTS", artifacts)
        .envs(envs.iter().copied())
        .arg(script)
        .args(args.iter().map(|a| a.as_ref()))
        .output()
        .unwrap_or_else(|e| panic!("cannot run node: {e}"));
    let stdout = text(&output.stdout);
    assert!(
        output.status.success(),
        "browser test {script} failed:\n{stdout}\n{}\n(screenshots in {})",
        text(&output.stderr),
        artifacts.display()
    );
    stdout
}

/// `subsume user add NAME --role ROLE [--platform P].. --password-stdin`
/// on the store at `store`.
pub fn add_user(store: &Path, name: &str, role: &str, platforms: &[&str], password: &str) {
    let mut command = subsume();
    command.args(["user", "add", name, "--role", role, "--password-stdin", "--store"]).arg(store);
    for platform in platforms {
        command.args(["--platform", platform]);
    }
    let mut child = command.stdin(Stdio::piped()).stderr(Stdio::null()).spawn().unwrap();
    child.stdin.take().unwrap().write_all(format!("{password}\n").as_bytes()).unwrap();
    assert!(child.wait().unwrap().success(), "subsume user add {name} failed");
}

/// Logs `name` in to the portal at `address`: the session token.
pub fn login(address: &str, name: &str, password: &str) -> String {
    let body = serde_json::json!({ "name": name, "password": password }).to_string();
    let (status, json) = http(address, "POST", "/api/v1/login", None, body.as_bytes());
    assert_eq!(status, 200, "{json}");
    json["token"].as_str().unwrap().to_string()
}

/// Every file under `store` with its bytes, sorted, leaving out the files
/// and folders named in `except` (e.g. "recordings", "audit.log").
pub fn store_snapshot(except: &[&str], store: &Path) -> Vec<(PathBuf, Vec<u8>)> {
    let mut files = Vec::new();
    let mut dirs = vec![store.to_path_buf()];
    while let Some(dir) = dirs.pop() {
        for entry in std::fs::read_dir(&dir).unwrap() {
            let path = entry.unwrap().path();
            if path.file_name().is_some_and(|n| except.iter().any(|e| n == *e)) {
                continue;
            }
            if path.is_dir() {
                dirs.push(path);
            } else {
                files.push((path.clone(), std::fs::read(&path).unwrap()));
            }
        }
    }
    files.sort();
    files
}

/// What the `mcap` package (PyPI; tests/python/mcap_reader.py) reads in
/// `file`: with `truncated`, a file a killed host left; every message of
/// the `values` topics too.
pub fn read_mcap(file: &Path, truncated: bool, values: &[&str]) -> Json {
    let mut command = Command::new(python());
    command.arg(repo_root().join("tests/python/mcap_reader.py")).arg(file);
    if truncated {
        command.arg("--truncated");
    }
    for topic in values {
        command.args(["--values", topic]);
    }
    let output = command.output().unwrap();
    assert!(output.status.success(), "mcap reader failed on {}: {}", file.display(), text(&output.stderr));
    serde_json::from_slice(&output.stdout).unwrap()
}

/// An operator on the teleoperation line protocol over TCP, answering
/// pings after `pong_delay`.
pub struct Operator {
    pub reader: BufReader<TcpStream>,
    writer: TcpStream,
    pub pong_delay: Duration,
    started: Instant,
    seq: u64,
    /// The CONTROL notices received so far (they come when the arbiter's
    /// verdict changes, between the replies).
    pub controls: Vec<String>,
}

impl Operator {
    /// Connects to the platform at `address`: returns the operator and the
    /// HELLO line.
    pub fn connect_to(address: &str) -> (Operator, String) {
        Operator::over(TcpStream::connect(address).unwrap())
    }

    /// The operator on `stream` (e.g. from a chosen source address), and
    /// the HELLO line.
    pub fn over(stream: TcpStream) -> (Operator, String) {
        stream.set_read_timeout(Some(Duration::from_secs(15))).unwrap();
        let mut operator = Operator {
            reader: BufReader::new(stream.try_clone().unwrap()),
            writer: stream,
            pong_delay: Duration::ZERO,
            started: Instant::now(),
            seq: 0,
            controls: Vec::new(),
        };
        let hello = operator.line();
        (operator, hello)
    }

    pub fn send(&mut self, line: &str) {
        self.writer.write_all(format!("{line}\n").as_bytes()).unwrap();
    }

    /// The next line, whatever it is.
    pub fn line(&mut self) -> String {
        let mut line = String::new();
        let n = self.reader.read_line(&mut line).unwrap_or(0);
        assert!(n > 0, "the host closed the connection");
        line.trim_end().to_string()
    }

    /// The next line that is neither a PING (answered on the way) nor a
    /// CONTROL notice (kept in `controls`).
    pub fn reply(&mut self) -> String {
        loop {
            let line = self.not_ping();
            if line.starts_with("CONTROL ") {
                self.controls.push(line);
            } else {
                return line;
            }
        }
    }

    /// The next OK or ERR line (PINGs answered, every other notice skipped).
    pub fn answer(&mut self) -> String {
        loop {
            let line = self.not_ping();
            if line.starts_with("OK ") || line.starts_with("ERR ") {
                return line;
            }
        }
    }

    /// Sends `line` and returns its [`answer`](Self::answer).
    pub fn say(&mut self, line: &str) -> String {
        self.send(line);
        self.answer()
    }

    /// The next line that is not a PING (answered on the way).
    pub fn not_ping(&mut self) -> String {
        loop {
            let line = self.line();
            match line.strip_prefix("PING ") {
                Some(nonce) => {
                    std::thread::sleep(self.pong_delay);
                    let nonce = nonce.to_string();
                    self.send(&format!("PONG {nonce}"));
                }
                None => return line,
            }
        }
    }

    /// Reads (answering PINGs) until a CONTROL notice starting with
    /// `prefix` has arrived; returns it.
    pub fn await_control(&mut self, prefix: &str) -> String {
        loop {
            if let Some(found) = self.controls.iter().find(|c| c.starts_with(prefix)) {
                return found.clone();
            }
            let line = self.not_ping();
            if line.starts_with("CONTROL ") {
                self.controls.push(line);
            } else {
                assert!(line.starts_with("DROP") || line.starts_with("RTT") || line.starts_with("MODE"), "{line}");
            }
        }
    }

    /// Logs in and waits for the first measurement; returns the RTT line.
    pub fn login(&mut self, name: &str, token: &str) -> String {
        self.send(&format!("AUTH {name} {token}"));
        assert_eq!(self.reply(), format!("OK authenticated as {name}; measuring the round-trip time"));
        let rtt = self.reply();
        assert!(rtt.starts_with("RTT "), "{rtt}");
        rtt
    }

    /// Sends `command` with the next sequence number and the time since
    /// the connection.
    pub fn command(&mut self, command: &str) {
        self.seq += 1;
        let ms = self.started.elapsed().as_millis();
        let line = format!("CMD {} {ms} {command}", self.seq);
        self.send(&line);
    }
}

/// A program in a real terminal: `command_line` run by `script` (from
/// bsdutils) in a pseudo-terminal of its own; what is written to it arrives
/// as key presses, and its screen output is collected.
pub struct Terminal {
    pub child: Child,
    keys: std::process::ChildStdin,
    screen: std::sync::mpsc::Receiver<String>,
    /// Everything the program showed so far.
    pub seen: String,
}

impl Terminal {
    pub fn start(command_line: &str) -> Terminal {
        let mut child = Command::new("script")
            .args(["-qfec", command_line, "/dev/null"])
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::null())
            .spawn()
            .expect("script (from bsdutils) runs the client in a pseudo-terminal");
        let keys = child.stdin.take().unwrap();
        let mut screen_out = child.stdout.take().unwrap();
        let (screen_tx, screen) = std::sync::mpsc::channel::<String>();
        std::thread::spawn(move || {
            let mut buffer = [0u8; 4096];
            while let Ok(n) = screen_out.read(&mut buffer) {
                if n == 0 || screen_tx.send(text(&buffer[..n])).is_err() {
                    break;
                }
            }
        });
        Terminal { child, keys, screen, seen: String::new() }
    }

    /// Waits up to 20 s until the program has shown `text`.
    pub fn wait_for(&mut self, text: &str) {
        let deadline = Instant::now() + Duration::from_secs(20);
        while !self.seen.contains(text) {
            assert!(Instant::now() < deadline, "the client never showed {text:?}: {:?}", self.seen);
            if let Ok(chunk) = self.screen.recv_timeout(Duration::from_millis(100)) {
                self.seen.push_str(&chunk);
            }
        }
    }

    /// Types `keys`.
    pub fn press(&mut self, keys: &[u8]) {
        self.keys.write_all(keys).unwrap();
        self.keys.flush().unwrap();
    }

    /// Waits up to 10 s for the program to quit.
    pub fn wait_for_quit(&mut self) -> ExitStatus {
        let deadline = Instant::now() + Duration::from_secs(10);
        loop {
            if let Some(status) = self.child.try_wait().unwrap() {
                return status;
            }
            while let Ok(chunk) = self.screen.try_recv() {
                self.seen.push_str(&chunk);
            }
            if Instant::now() >= deadline {
                let tail: String = self.seen.chars().rev().take(600).collect::<Vec<_>>().into_iter().rev().collect();
                panic!("the client did not quit; its screen ended with {tail:?}\n{}", children_of(self.child.id()));
            }
            std::thread::sleep(Duration::from_millis(20));
        }
    }
}

impl Drop for Terminal {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// `component` (ticking at `hz`) kept its rate beside an offender that spent
/// `offender_ms` in its calls: it stayed on its schedule's grid (ticks the
/// loop could not run are counted as missed, not lost), and missed no more
/// ticks than the machine and the offender explain. The machine's share is
/// the time the control thread waited for a CPU (`loop_lateness.
/// waited_for_cpu_ms`, the kernel's run delay): near zero on an idle machine,
/// large while other processes keep the cores busy. Ticks missed beyond
/// both (and beyond `tolerance`, the share allowed on an idle machine)
/// would mean the host held the loop itself, e.g. while faulting the
/// offender.
pub fn kept_its_rate(
    report: &serde_json::Value,
    component: &serde_json::Value,
    hz: f64,
    tolerance: f64,
    offender_ms: f64,
    what: &str,
) {
    let expected = report["duration_s"].as_f64().unwrap() * hz;
    let ticks = component["ticks"].as_f64().unwrap();
    let missed = component["missed_ticks"].as_f64().unwrap();
    let waited_ms = report["loop_lateness"]["waited_for_cpu_ms"].as_f64().unwrap();
    // Missed ticks are counted at the next cycle: the ones due after the
    // loop's last cycle, when it waited for a cpu at the end of the run
    // (which `duration_s` counts), are in neither figure.
    let uncounted = waited_ms * hz / 1e3;
    assert!(
        ticks + missed - expected <= 2.0 && expected - (ticks + missed) <= 2.0 + uncounted,
        "{what}: {ticks} ticks and {missed} missed, expected {expected} on the schedule \
         (up to {uncounted:.0} fewer while the loop waited {waited_ms} ms for a cpu)"
    );
    let explained = (waited_ms + offender_ms) * hz / 1e3 + 2.0;
    let allowed = explained.max(expected * tolerance);
    assert!(
        missed <= allowed,
        "{what}: the healthy component missed {missed} of {expected} ticks; the loop waited {waited_ms} ms \
         for a cpu and the offender held it {offender_ms} ms, which explain {explained:.0}: {}",
        report["loop_lateness"]
    );
}

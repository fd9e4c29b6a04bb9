//! Shared by the integration tests: where the repository is, and the Rust
//! guest components, built once per test process from guest-components/rust.

#![allow(dead_code, clippy::panic, clippy::unwrap_used, clippy::expect_used)]

use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::OnceLock;

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

/// A compile cache shared by the tests of this checkout.
/// The tests' own Python (the virtualenv scripts/setup installs, with the
/// independent implementations the tests talk to).
pub fn python() -> PathBuf {
    let python = repo_root().join("tests/python/.venv/bin/python");
    assert!(python.is_file(), "{} is missing: run scripts/setup first", python.display());
    python
}

pub fn cache_dir() -> PathBuf {
    repo_root().join("target/test-component-cache")
}

/// The far end of a pseudo-terminal playing a motor controller: records
/// every line the host writes, with the time it arrived, and every byte.
pub struct MotorRecorder {
    master: serialport::TTYPort,
    pending: String,
    /// Each complete line and when it was read.
    pub lines: Vec<(std::time::Instant, String)>,
    /// Every byte read, in order (binary protocols have no lines).
    pub bytes: Vec<u8>,
    /// When the last read returned, and the longest time between two reads
    /// returning: a line's time is late by at most that (a read waits at
    /// most [`MotorRecorder::READ_TIMEOUT`], so more means this thread
    /// waited for a CPU).
    last_read: Option<std::time::Instant>,
    pub max_read_gap: std::time::Duration,
}

impl MotorRecorder {
    /// A new pseudo-terminal; the host opens the returned device path.
    pub fn new() -> (MotorRecorder, serialport::TTYPort, String) {
        use serialport::SerialPort;
        let (mut master, slave) = serialport::TTYPort::pair().unwrap_or_else(|e| panic!("no pseudo-terminal: {e}"));
        let _ = master.set_timeout(MotorRecorder::READ_TIMEOUT);
        let device = slave.name().unwrap_or_default();
        let recorder = MotorRecorder {
            master,
            pending: String::new(),
            lines: Vec::new(),
            bytes: Vec::new(),
            last_read: None,
            max_read_gap: std::time::Duration::ZERO,
        };
        (recorder, slave, device)
    }

    /// The longest a read waits for bytes.
    pub const READ_TIMEOUT: std::time::Duration = std::time::Duration::from_millis(10);

    /// Reads what has arrived (waiting at most [`Self::READ_TIMEOUT`]).
    pub fn read(&mut self) {
        let mut buffer = [0u8; 256];
        let read = std::io::Read::read(&mut self.master, &mut buffer);
        let now = std::time::Instant::now();
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
        let _ = std::io::Write::write_all(&mut self.master, bytes);
    }

    /// Reads while `going` says so.
    pub fn read_while(&mut self, mut going: impl FnMut() -> bool) {
        while going() {
            self.read();
        }
    }
}

/// `subsume` run from the repository root with the tests' compile cache,
/// `RUST_LOG=info` and `NO_COLOR=1`; the caller adds the subcommand.
pub fn subsume() -> Command {
    let mut command = Command::new(env!("CARGO_BIN_EXE_subsume"));
    command.current_dir(repo_root()).arg("--cache-dir").arg(cache_dir()).env("RUST_LOG", "info").env("NO_COLOR", "1");
    command
}

/// A running host whose stderr a thread reads into a log, so a test can
/// wait for what the host announces (its addresses) and show the whole log
/// when something is missing.
pub struct HostProcess {
    pub child: std::process::Child,
    log: std::sync::Arc<(std::sync::Mutex<Vec<String>>, std::sync::Condvar)>,
}

impl HostProcess {
    /// Spawns `command` (stdout discarded, stderr read).
    pub fn spawn(mut command: Command) -> HostProcess {
        use std::io::BufRead;
        let mut child = command
            .stdout(std::process::Stdio::null())
            .stderr(std::process::Stdio::piped())
            .spawn()
            .unwrap_or_else(|e| panic!("cannot start the host: {e}"));
        let stderr = child.stderr.take().unwrap_or_else(|| panic!("no stderr pipe"));
        let log = std::sync::Arc::new((std::sync::Mutex::new(Vec::new()), std::sync::Condvar::new()));
        let writer = log.clone();
        std::thread::spawn(move || {
            for line in std::io::BufReader::new(stderr).lines().map_while(Result::ok) {
                let (lines, grew) = &*writer;
                lines.lock().unwrap_or_else(|e| e.into_inner()).push(line);
                grew.notify_all();
            }
        });
        HostProcess { child, log }
    }

    /// Waits up to `timeout` for a log line holding `marker` and returns the
    /// word after it (up to whitespace); panics with the log if none came.
    pub fn word_after(&self, marker: &str, timeout: std::time::Duration) -> String {
        let deadline = std::time::Instant::now() + timeout;
        let (lines, grew) = &*self.log;
        let mut lines = lines.lock().unwrap_or_else(|e| e.into_inner());
        loop {
            let found = lines.iter().find_map(|line| line.split_once(marker).map(|(_, rest)| rest.to_string()));
            if let Some(rest) = found {
                return rest.split_whitespace().next().unwrap_or_default().to_string();
            }
            let now = std::time::Instant::now();
            if now >= deadline {
                panic!("the host never said '{marker}':\n{}", lines.join("\n"));
            }
            lines = grew.wait_timeout(lines, deadline - now).unwrap_or_else(|e| e.into_inner()).0;
        }
    }

    /// Every stderr line so far.
    pub fn log(&self) -> String {
        self.log.0.lock().unwrap_or_else(|e| e.into_inner()).join("\n")
    }
}

impl Drop for HostProcess {
    /// A test that ends early (or fails) leaves no host behind.
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// One HTTP/1.1 request to the portal at `address`: (status, JSON body,
/// or null when the body is not JSON).
pub fn http(address: &str, method: &str, path: &str, token: Option<&str>, body: &[u8]) -> (u16, serde_json::Value) {
    let mut stream = std::net::TcpStream::connect(address).unwrap();
    stream.set_read_timeout(Some(std::time::Duration::from_secs(30))).unwrap();
    let auth = token.map(|t| format!("Authorization: Bearer {t}\r\n")).unwrap_or_default();
    let head = format!(
        "{method} {path} HTTP/1.1\r\nHost: {address}\r\n{auth}Content-Length: {}\r\nConnection: close\r\n\r\n",
        body.len()
    );
    std::io::Write::write_all(&mut stream, head.as_bytes()).unwrap();
    let _ = std::io::Write::write_all(&mut stream, body);
    let mut response = Vec::new();
    let _ = std::io::Read::read_to_end(&mut stream, &mut response);
    let text = String::from_utf8_lossy(&response);
    let status = text.split(' ').nth(1).and_then(|s| s.parse().ok()).unwrap_or(0);
    let body = text.split("\r\n\r\n").nth(1).unwrap_or("");
    (status, serde_json::from_str(body).unwrap_or(serde_json::Value::Null))
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

/// Runs `tests/browser/SCRIPT ARGS..` (node with playwright-core driving
/// Debian's Chromium, both installed by scripts/setup) with `envs`, and
/// ARTIFACTS set to `artifacts`, where it saves its screenshots. Panics with
/// all it printed unless it succeeds; returns its stdout.
pub fn browser(script: &str, artifacts: &Path, envs: &[(&str, &str)], args: &[&dyn AsRef<std::ffi::OsStr>]) -> String {
    let dir = repo_root().join("tests/browser");
    assert!(
        dir.join("node_modules/playwright-core").is_dir(),
        "run scripts/setup first: it installs playwright-core and chromium"
    );
    let output = Command::new("node")
        .current_dir(&dir)
        .env("ARTIFACTS", artifacts)
        .envs(envs.iter().copied())
        .arg(script)
        .args(args.iter().map(|a| a.as_ref()))
        .output()
        .unwrap_or_else(|e| panic!("cannot run node: {e}"));
    let stdout = String::from_utf8_lossy(&output.stdout).into_owned();
    assert!(
        output.status.success(),
        "browser test {script} failed:\n{stdout}\n{}\n(screenshots in {})",
        String::from_utf8_lossy(&output.stderr),
        artifacts.display()
    );
    stdout
}

/// `subsume user add NAME --role ROLE [--platform P].. --password-stdin`
/// on the store at `store`.
pub fn add_user(store: &Path, name: &str, role: &str, platforms: &[&str], password: &str) {
    use std::io::Write;
    let mut command = Command::new(env!("CARGO_BIN_EXE_subsume"));
    command.args(["user", "add", name, "--role", role, "--password-stdin", "--store"]).arg(store);
    for platform in platforms {
        command.args(["--platform", platform]);
    }
    let mut child = command.stdin(std::process::Stdio::piped()).stderr(std::process::Stdio::null()).spawn().unwrap();
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

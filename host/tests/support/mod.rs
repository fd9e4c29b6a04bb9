//! Shared by the integration tests: where the repository is, and the Rust
//! guest components, built once per test process from guest-components/rust.

#![allow(dead_code, clippy::panic)]

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
}

impl MotorRecorder {
    /// A new pseudo-terminal; the host opens the returned device path.
    pub fn new() -> (MotorRecorder, serialport::TTYPort, String) {
        use serialport::SerialPort;
        let (mut master, slave) = serialport::TTYPort::pair().unwrap_or_else(|e| panic!("no pseudo-terminal: {e}"));
        let _ = master.set_timeout(std::time::Duration::from_millis(10));
        let device = slave.name().unwrap_or_default();
        (MotorRecorder { master, pending: String::new(), lines: Vec::new(), bytes: Vec::new() }, slave, device)
    }

    /// Reads what has arrived (waiting at most the port's 10 ms timeout).
    pub fn read(&mut self) {
        let mut buffer = [0u8; 256];
        if let Ok(n) = std::io::Read::read(&mut self.master, &mut buffer) {
            self.bytes.extend_from_slice(&buffer[..n]);
            self.pending.push_str(&String::from_utf8_lossy(&buffer[..n]));
            while let Some(end) = self.pending.find('\n') {
                self.lines.push((std::time::Instant::now(), self.pending[..end].to_string()));
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

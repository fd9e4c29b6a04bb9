//! Every option that writes a file or a folder, given a path that is not a
//! regular file (fsutil's rule): a character device (the null device's
//! numbers, made by the test in its own folder as root; never the real
//! /dev/null) is written into and is still that device afterwards; a FIFO
//! (read by the test) gets the bytes and is still a FIFO; a folder option
//! refuses both and names the path; a file option refuses a directory.
//! One table, a row per option.

use std::ffi::OsString;
use std::io::Write as _;
use std::os::unix::fs::{FileTypeExt, MetadataExt, OpenOptionsExt};
use std::path::Path;
use std::process::Stdio;
use std::thread::JoinHandle;
use std::time::Duration;

use crate::support::{FREE_TELEOP_PORTS, subsume, text, wait_for_exit};

/// What an option writes, and how the test knows the bytes are whole.
enum Writes {
    /// A file: these bytes are what it should be.
    File(fn(&[u8]) -> Result<(), String>),
    /// A folder (downloads, projects): a device or a FIFO is refused.
    Folder,
}

struct OutputOption {
    /// The option as a user types it.
    name: &'static str,
    /// The name the test gives its device, FIFO or directory.
    file_name: &'static str,
    /// The command line, the output at `path`.
    args: fn(path: &Path) -> Vec<OsString>,
    writes: Writes,
}

fn os(args: &[&str], path: &Path, after: &[&str]) -> Vec<OsString> {
    args.iter()
        .map(OsString::from)
        .chain([path.as_os_str().to_owned()])
        .chain(after.iter().map(OsString::from))
        .collect()
}

/// A second of the demo robot on simulated time, writing `flag` to `path`.
fn short_run(command: &str, flag: &str, path: &Path) -> Vec<OsString> {
    let http = if command == "dev" { "127.0.0.1:0" } else { "off" };
    let before = [command, "config/demo.xml", "--http", http, "--speed", "max", "--duration", "1", flag];
    os(&before, path, &FREE_TELEOP_PORTS)
}

// Nothing listens here: a folder option is checked before anything is sent.
const NO_LAB: &str = "127.0.0.1:9";
const LOGIN: [&str; 4] = ["--user", "ana", "--password", "not-sent"];

fn json_has(bytes: &[u8], key: &str) -> Result<(), String> {
    let json: serde_json::Value = serde_json::from_slice(bytes).map_err(|e| format!("not JSON: {e}"))?;
    json.get(key).map(drop).ok_or_else(|| format!("no {key} in {json}"))
}

/// A whole MCAP file: the magic at both ends.
fn whole_mcap(bytes: &[u8]) -> Result<(), String> {
    const MAGIC: &[u8] = b"\x89MCAP0\r\n";
    if bytes.len() > 2 * MAGIC.len() && bytes.starts_with(MAGIC) && bytes.ends_with(MAGIC) {
        Ok(())
    } else {
        Err(format!("not a whole MCAP file ({} bytes)", bytes.len()))
    }
}

fn options() -> Vec<OutputOption> {
    vec![
        OutputOption {
            name: "run --report",
            file_name: "report",
            args: |p| short_run("run", "--report", p),
            writes: Writes::File(|b| json_has(b, "format")),
        },
        OutputOption {
            name: "dev --report",
            file_name: "report",
            args: |p| short_run("dev", "--report", p),
            writes: Writes::File(|b| json_has(b, "format")),
        },
        OutputOption {
            name: "run --verdict",
            file_name: "verdict",
            args: |p| short_run("run", "--verdict", p),
            writes: Writes::File(|b| json_has(b, "passed")),
        },
        OutputOption {
            name: "run --record",
            file_name: "null.mcap",
            args: |p| short_run("run", "--record", p),
            writes: Writes::File(whole_mcap),
        },
        OutputOption {
            name: "lab results -o",
            file_name: "results",
            args: |p| os(&["lab", "results", "1", NO_LAB, "-o"], p, &LOGIN),
            writes: Writes::Folder,
        },
        OutputOption {
            name: "lab kit -o",
            file_name: "kit",
            args: |p| os(&["lab", "kit", NO_LAB, "-o"], p, &LOGIN),
            writes: Writes::Folder,
        },
        OutputOption {
            name: "lab submit --results",
            file_name: "results",
            args: |p| os(&["lab", "submit", NO_LAB, "--duration", "5", "--results"], p, &LOGIN),
            writes: Writes::Folder,
        },
        OutputOption {
            name: "new --dir",
            file_name: "project",
            args: |p| os(&["new", "mine", "--lang", "rust", "--dir"], p, &[]),
            writes: Writes::Folder,
        },
    ]
}

/// The test's own null device in `dir`.
fn make_null(path: &Path) {
    let made = std::process::Command::new("mknod").arg(path).args(["c", "1", "3"]).status().unwrap();
    assert!(made.success(), "mknod {} (the tests run as root)", path.display());
}

fn is_null(path: &Path) -> bool {
    std::fs::symlink_metadata(path).is_ok_and(|m| m.file_type().is_char_device() && m.rdev() == libc_makedev(1, 3))
}

/// `makedev(1, 3)` as Linux encodes it.
fn libc_makedev(major: u64, minor: u64) -> u64 {
    ((major & 0xfff) << 8) | (minor & 0xff) | ((minor & !0xff) << 12) | ((major & !0xfff) << 32)
}

/// Reads the FIFO at `path` to its end on a thread of its own.
fn read_fifo(path: &Path) -> JoinHandle<Vec<u8>> {
    let path = path.to_path_buf();
    std::thread::spawn(move || std::fs::read(&path).unwrap())
}

/// The reader's bytes once the writer is gone; a reader still waiting for
/// a writer that never came is let go (and reads nothing).
fn fifo_bytes(path: &Path, reader: JoinHandle<Vec<u8>>) -> Vec<u8> {
    while !reader.is_finished() {
        let mut nonblocking = std::fs::OpenOptions::new();
        nonblocking.write(true).custom_flags(0o4000); // O_NONBLOCK: only while the reader waits
        if let Ok(mut file) = nonblocking.open(path) {
            let _ = file.flush();
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    reader.join().unwrap()
}

/// Runs `args`; (succeeded, stderr).
fn run(option: &OutputOption, path: &Path, store: &Path) -> (bool, String) {
    let mut child = subsume()
        .env("SUBSUME_STORE", store)
        .args((option.args)(path))
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let stderr = child.stderr.take().unwrap();
    let reader = std::thread::spawn(move || std::io::read_to_string(stderr).unwrap_or_default());
    let status = wait_for_exit(&mut child, Duration::from_secs(120));
    (status.success(), reader.join().unwrap())
}

#[test]
fn every_output_option_writes_into_a_device_or_fifo_and_never_replaces_one() {
    for option in options() {
        let dir = tempfile::tempdir().unwrap();
        let store = dir.path().join("store");
        let name = option.name;

        // A character device: still the same device afterwards.
        let device_dir = dir.path().join("device");
        std::fs::create_dir(&device_dir).unwrap();
        let null = device_dir.join(option.file_name);
        make_null(&null);
        let (ok, log) = run(&option, &null, &store);
        assert!(is_null(&null), "{name}: the device was replaced\n{log}");
        assert_eq!(std::fs::read_dir(&device_dir).unwrap().count(), 1, "{name}: something was left beside it\n{log}");
        match option.writes {
            Writes::File(_) => assert!(ok, "{name} into a character device failed\n{log}"),
            Writes::Folder => {
                assert!(!ok, "{name} accepted a character device\n{log}");
                assert!(log.contains(null.to_str().unwrap()), "{name}: the error names the path\n{log}");
            }
        }

        // A FIFO: it gets the whole output, and stays a FIFO.
        let fifo_dir = dir.path().join("fifo");
        std::fs::create_dir(&fifo_dir).unwrap();
        let fifo = fifo_dir.join(option.file_name);
        let made = std::process::Command::new("mkfifo").arg(&fifo).status().unwrap();
        assert!(made.success());
        let reader = read_fifo(&fifo);
        let (ok, log) = run(&option, &fifo, &store);
        let bytes = fifo_bytes(&fifo, reader);
        assert!(std::fs::symlink_metadata(&fifo).unwrap().file_type().is_fifo(), "{name}: the FIFO was replaced");
        assert_eq!(std::fs::read_dir(&fifo_dir).unwrap().count(), 1, "{name}: something was left beside it\n{log}");
        match option.writes {
            Writes::File(whole) => {
                assert!(ok, "{name} into a FIFO failed\n{log}");
                whole(&bytes).unwrap_or_else(|e| panic!("{name}: the FIFO got {e}\n{log}"));
            }
            Writes::Folder => {
                assert!(!ok, "{name} accepted a FIFO\n{log}");
                assert!(bytes.is_empty(), "{name} wrote into the FIFO");
                assert!(log.contains(fifo.to_str().unwrap()), "{name}: the error names the path\n{log}");
            }
        }

        // A file option given a directory refuses it, naming it, and
        // leaves it empty.
        if let Writes::File(_) = option.writes {
            let folder = dir.path().join("folder").join(option.file_name);
            std::fs::create_dir_all(&folder).unwrap();
            let (ok, log) = run(&option, &folder, &store);
            assert!(!ok, "{name} accepted a directory\n{log}");
            let said = format!("{} is a directory", folder.display());
            assert!(log.contains(&said), "{name}: the error says {said:?}\n{log}");
            assert!(std::fs::read_dir(&folder).unwrap().next().is_none(), "{name} wrote into the directory");
            assert_eq!(
                std::fs::read_dir(folder.parent().unwrap()).unwrap().count(),
                1,
                "{name}: a temporary file left"
            );
        }
    }
}

/// `/dev/stdout` works as an output: the report arrives on standard output.
#[test]
fn a_report_to_dev_stdout_arrives_on_standard_output() {
    let output = subsume().args(short_run("run", "--report", Path::new("/dev/stdout"))).output().unwrap();
    assert!(output.status.success(), "{}", text(&output.stderr));
    let stdout = text(&output.stdout);
    let start = stdout.find('{').unwrap_or_else(|| panic!("no report on stdout: {stdout}"));
    json_has(&stdout.as_bytes()[start..], "format").unwrap_or_else(|e| panic!("{e}: {stdout}"));
}

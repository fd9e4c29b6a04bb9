#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic)]
//! Memory end to end: the built binary running the demo with its portal,
//! operators logging in over real loopback TCP, the host's RSS read from
//! /proc. Each login checks the portal's users (an argon2id hash with
//! 19 MiB of working memory); that memory must go back when the hash is
//! done, not stay resident in the allocator (issue 15).

mod support;

use std::io::{BufRead, BufReader, Write};
use std::net::TcpStream;
use std::process::{Command, Stdio};
use std::time::Duration;

const PASSWORD: &str = "memory-test-password-0123";
/// The operator in config/demo-operators.
const OPERATOR: &str = "AUTH demo demo-token-change-me\n";
/// RSS the host may gain over 10 logins: a fraction of one login's 19 MiB
/// (before the fix it gained ~58 MiB).
const MAX_GROWTH_KIB: u64 = 12 << 10;

fn rss_kib(pid: u32) -> u64 {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).unwrap();
    let line = status.lines().find(|l| l.starts_with("VmRSS:")).unwrap();
    line.split_whitespace().nth(1).unwrap().parse().unwrap()
}

fn login(address: &str) {
    let stream = TcpStream::connect(address).unwrap();
    stream.set_read_timeout(Some(Duration::from_secs(30))).unwrap();
    let mut reader = BufReader::new(stream.try_clone().unwrap());
    let mut line = String::new();
    reader.read_line(&mut line).unwrap();
    assert!(line.starts_with("HELLO subsume "), "{line}");
    (&stream).write_all(OPERATOR.as_bytes()).unwrap();
    line.clear();
    reader.read_line(&mut line).unwrap();
    assert!(line.starts_with("OK"), "login: {line}");
}

#[test]
fn operator_logins_do_not_keep_the_password_hash_memory() {
    support::guest_dir();
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store");
    let mut add = Command::new(env!("CARGO_BIN_EXE_subsume"))
        .arg("--store")
        .arg(&store)
        .args(["user", "add", "admin", "--role", "admin", "--password-stdin"])
        .stdin(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    add.stdin.take().unwrap().write_all(format!("{PASSWORD}\n").as_bytes()).unwrap();
    assert!(add.wait().unwrap().success());
    let mut command = support::subsume();
    command.arg("--store").arg(&store).env_remove("SUBSUME_HTTP");
    command.args(["run", "config/demo.xml", "--http", "127.0.0.1:0", "--duration", "120"]);
    command.args(["--param", "teleop.listen=127.0.0.1:0", "--param", "teleop.websocket=127.0.0.1:0"]);
    let host = support::HostProcess::spawn(command);
    let pid = host.child.id();
    let address = host.word_after("teleoperation on tcp ", Duration::from_secs(60));
    std::thread::sleep(Duration::from_secs(1));
    let before = rss_kib(pid);
    for _ in 0..10 {
        login(&address);
    }
    std::thread::sleep(Duration::from_millis(500));
    let after = rss_kib(pid);
    assert!(
        after.saturating_sub(before) <= MAX_GROWTH_KIB,
        "10 operator logins took the host from {before} KiB to {after} KiB of RSS"
    );
}

//! Memory end to end: the built binary running the demo with its portal,
//! operators logging in over real loopback TCP, the host's RSS read from
//! /proc. Each login checks the portal's users (an argon2id hash with
//! 19 MiB of working memory); that memory must go back when the hash is
//! done, not stay resident in the allocator (issue 15).

use std::time::Duration;

use crate::support::{self, FREE_TELEOP_PORTS, Operator, subsume};

const PASSWORD: &str = "memory-test-password-0123";
/// The operator in config/demo-operators.
const OPERATOR: &str = "AUTH demo demo-token-change-me";
/// RSS the host may gain over 10 logins: a fraction of one login's 19 MiB
/// (before the fix it gained ~58 MiB).
const MAX_GROWTH_KIB: u64 = 12 << 10;

fn rss_kib(pid: u32) -> u64 {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).unwrap();
    let line = status.lines().find(|l| l.starts_with("VmRSS:")).unwrap();
    line.split_whitespace().nth(1).unwrap().parse().unwrap()
}

fn login(address: &str) {
    let (mut operator, hello) = Operator::connect_to(address);
    assert!(hello.starts_with("HELLO subsume "), "{hello}");
    operator.send(OPERATOR);
    let line = operator.line();
    assert!(line.starts_with("OK"), "login: {line}");
}

#[test]
fn operator_logins_do_not_keep_the_password_hash_memory() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store");
    support::add_user(&store, "admin", "admin", &[], PASSWORD);
    let mut command = subsume();
    command.arg("--store").arg(&store);
    command.args(["run", "config/demo.xml", "--http", "127.0.0.1:0", "--duration", "120"]).args(FREE_TELEOP_PORTS);
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

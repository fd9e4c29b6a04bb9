//! Flags several commands share, declared once and flattened into each, and
//! the value parsers that check a flag's range against the library's named
//! limit, so a bad value is refused before anything starts.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::time::Duration;

use subsume::config::ParamOverride;
use subsume::runtime::lockstep::Pace;

/// `--param COMPONENT.PARAM=VALUE`, repeatable.
#[derive(clap::Args, Clone, Debug, Default)]
pub struct ParamFlags {
    /// Set a component parameter, overriding the robot file (repeatable).
    #[arg(long = "param", value_name = "COMPONENT.PARAM=VALUE")]
    pub params: Vec<ParamOverride>,
}

/// How long and how fast a robot runs, and where its report goes (`run`,
/// `dev`).
#[derive(clap::Args, Clone, Debug)]
pub struct RobotFlags {
    /// Stop after this many seconds (simulated seconds with --speed).
    #[arg(long, value_name = "SECONDS", value_parser = positive_seconds)]
    pub duration: Option<Duration>,
    /// Run on simulated time: N times real time, or `max` (lock-step, as
    /// fast as the CPU allows). Same inputs, same results.
    #[arg(long, value_name = "N|max")]
    pub speed: Option<Pace>,
    /// Write a JSON report here when stopped (see docs/report.md).
    #[arg(long, value_name = "FILE")]
    pub report: Option<PathBuf>,
    #[command(flatten)]
    pub params: ParamFlags,
}

/// Logging in to a running host's portal (`estop`, `release`, `deploy`).
#[derive(clap::Args, Clone, Debug)]
pub struct LoginFlags {
    /// The portal's address (HOST:PORT or http://HOST:PORT).
    pub host: String,
    /// The portal user to log in as.
    #[arg(long, env = "SUBSUME_USER")]
    pub user: String,
    /// Their password (or set SUBSUME_PASSWORD).
    #[arg(long, env = "SUBSUME_PASSWORD", hide_env_values = true)]
    pub password: String,
}

impl LoginFlags {
    /// Logs in to the portal and engages or releases its locks, printing
    /// what the host said.
    pub fn lock_action(self, action: subsume::portal::client::LockAction) -> anyhow::Result<std::process::ExitCode> {
        println!("{}", subsume::portal::client::lock_action(&self.host, &self.user, &self.password, action)?);
        Ok(std::process::ExitCode::SUCCESS)
    }
}

/// A listening address, or `off`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Listen {
    Off,
    On(SocketAddr),
}

impl Listen {
    pub fn address(self) -> Option<SocketAddr> {
        match self {
            Listen::Off => None,
            Listen::On(address) => Some(address),
        }
    }
}

/// `ADDRESS` or `off`.
pub(super) fn address_or_off(text: &str) -> Result<Listen, String> {
    if text == "off" {
        return Ok(Listen::Off);
    }
    text.parse().map(Listen::On).map_err(|e| format!("an address like 127.0.0.1:8080 or off, got '{text}': {e}"))
}

/// A number of seconds, finite and more than 0.
pub(super) fn positive_seconds(text: &str) -> Result<Duration, String> {
    match text.parse::<f64>() {
        Ok(s) if s.is_finite() && s > 0.0 => Ok(Duration::from_secs_f64(s)),
        _ => Err(format!("a positive number of seconds, got '{text}'")),
    }
}

/// A number of seconds within `min..=max`.
pub(super) fn seconds_within(text: &str, min: Duration, max: Duration) -> Result<Duration, String> {
    let (low, high) = (min.as_secs_f64(), max.as_secs_f64());
    match text.parse::<f64>() {
        Ok(s) if s.is_finite() && (low..=high).contains(&s) => Ok(Duration::from_secs_f64(s)),
        _ => Err(format!("must be between {low} and {high} seconds, got '{text}'")),
    }
}

/// `--stall-limit`: within the stall watchdog's limits.
pub(super) fn stall_limit(text: &str) -> Result<Duration, String> {
    use subsume::runtime::stall::{MAX_STALL_LIMIT, MIN_STALL_LIMIT};
    seconds_within(text, MIN_STALL_LIMIT, MAX_STALL_LIMIT)
}

/// `--poll`: within the file watcher's limits.
pub(super) fn poll(text: &str) -> Result<Duration, String> {
    use subsume::deploy::dev::{MAX_POLL, MIN_POLL};
    seconds_within(text, MIN_POLL, MAX_POLL)
}

/// `--control-fifo`: a `SCHED_FIFO` priority the kernel accepts.
pub(super) fn fifo_priority(text: &str) -> Result<i32, String> {
    use subsume::runtime::scheduling::FIFO_PRIORITIES;
    match text.parse::<i32>() {
        Ok(p) if FIFO_PRIORITIES.contains(&p) => Ok(p),
        _ => Err(format!("must be between {} and {}, got {text}", FIFO_PRIORITIES.start(), FIFO_PRIORITIES.end())),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn each_parser_takes_its_range_and_names_what_it_refused() {
        assert_eq!(positive_seconds("1.5"), Ok(Duration::from_millis(1500)));
        for bad in ["0", "-1", "inf", "NaN", "x"] {
            assert!(positive_seconds(bad).unwrap_err().contains(&format!("'{bad}'")), "{bad}");
        }
        assert_eq!(stall_limit("0.01"), Ok(Duration::from_millis(10)));
        assert_eq!(stall_limit("10"), Ok(Duration::from_secs(10)));
        assert_eq!(stall_limit("0.005"), Err("must be between 0.01 and 10 seconds, got '0.005'".into()));
        assert_eq!(poll("0.02"), Ok(Duration::from_millis(20)));
        assert!(poll("11").is_err());
        assert_eq!(fifo_priority("99"), Ok(99));
        assert_eq!(fifo_priority("100"), Err("must be between 1 and 99, got 100".into()));
        assert_eq!(address_or_off("off"), Ok(Listen::Off));
        assert_eq!(address_or_off("127.0.0.1:0").map(Listen::address), Ok(Some("127.0.0.1:0".parse().unwrap())));
        assert!(address_or_off("localhost").is_err());
    }
}

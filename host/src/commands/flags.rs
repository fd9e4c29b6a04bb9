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

/// Logging in to a running host's portal or a lab server's (`estop`,
/// `release`, `deploy`, `lab`), over https or, to loopback, plain http.
#[derive(clap::Args, Clone, Debug)]
pub struct LoginFlags {
    /// The portal's address: https://HOST[:PORT], or http://HOST:PORT or
    /// HOST:PORT for plain http (loopback only, unless
    /// --allow-plain-http).
    pub host: String,
    /// The portal user to log in as.
    #[arg(long, env = "SUBSUME_USER")]
    pub user: String,
    /// Their password (or set SUBSUME_PASSWORD).
    #[arg(long, env = "SUBSUME_PASSWORD", hide_env_values = true)]
    pub password: String,
    /// Trust the portal's certificate only if this authority (PEM) issued
    /// it: a lab's own CA. Without it, the system's trusted roots.
    #[arg(long, value_name = "FILE", env = "SUBSUME_CA")]
    pub ca: Option<PathBuf>,
    /// Send the password over plain http to an address other than
    /// loopback (anyone on the way can read it: only on a network you
    /// trust).
    #[arg(long)]
    pub allow_plain_http: bool,
}

impl LoginFlags {
    /// The client's login.
    pub fn login(self) -> subsume::portal::client::Login {
        subsume::portal::client::Login {
            host: self.host,
            user: self.user,
            password: self.password,
            ca: self.ca,
            allow_plain_http: self.allow_plain_http,
        }
    }

    /// Logs in to the portal and engages or releases its locks, printing
    /// what the host said.
    pub fn lock_action(self, action: subsume::portal::client::LockAction) -> anyhow::Result<std::process::ExitCode> {
        println!("{}", subsume::portal::client::lock_action(&self.login(), action)?);
        Ok(std::process::ExitCode::SUCCESS)
    }
}

/// `subsume run`'s settings for joining a lab of several robots
/// (docs/lab.md, "Several robots").
#[derive(clap::Args, Clone, Debug, Default, PartialEq)]
pub struct LabJoinFlags {
    /// Join this lab: its experiments come from its lab server only.
    #[arg(long, value_name = "NAME")]
    pub lab: Option<String>,
    /// The lab's shared secret (its first line) [default: STORE/lab.secret].
    #[arg(long, value_name = "FILE")]
    pub lab_secret: Option<PathBuf>,
    /// The Zenoh config (JSON5: TLS, user/password) of the lab's session.
    #[arg(long, value_name = "FILE")]
    pub lab_zenoh_config: Option<PathBuf>,
    /// Zenoh endpoints to connect to for the lab, comma-separated.
    #[arg(long, value_name = "ENDPOINTS", default_value = "")]
    pub lab_connect: String,
    /// Zenoh endpoints to listen on for the lab, comma-separated.
    #[arg(long, value_name = "ENDPOINTS", default_value = "")]
    pub lab_listen: String,
    /// This robot's name in the lab [default: the machine's host name].
    #[arg(long, value_name = "NAME")]
    pub lab_robot: Option<String>,
    /// Abort the lab's experiment and go back to the baseline after
    /// hearing nothing of the lab for this long (1 to 600).
    #[arg(long, value_name = "SECONDS", default_value = "5", value_parser = lab_lost)]
    pub lab_lost: Duration,
    /// How often the robot publishes its status to the lab (0.1 to 10).
    #[arg(long, value_name = "HZ", default_value = "1", value_parser = status_hz)]
    pub lab_status_hz: f64,
    /// Allow the lab's Zenoh link off loopback in plain text, or over TLS
    /// that authenticates nobody (a closed network only).
    #[arg(long)]
    pub lab_allow_plain: bool,
}

/// The Zenoh session of a lab's link: a config file and endpoints, as the
/// `zenoh` built-in takes them (docs/distributed.md).
pub fn lab_session(
    config: Option<PathBuf>,
    connect: &str,
    listen: &str,
    allow_plain: (bool, &str),
) -> anyhow::Result<subsume::bridge::session::SessionSettings> {
    let split = |text: &str| text.split(',').map(str::trim).filter(|s| !s.is_empty()).map(str::to_string).collect();
    let settings = subsume::bridge::session::SessionSettings {
        connect: split(connect),
        listen: split(listen),
        config,
        // The lab's bound, at the Zenoh layer too.
        max_message_bytes: Some(subsume::lab::wire::MAX_ZENOH_MESSAGE_BYTES),
    };
    // Off loopback, the lab's link is TLS that authenticates its peers
    // (mutual TLS or user/password), unless the owner allows otherwise.
    let exposure = subsume::bridge::session::link_exposure(&settings.zenoh_config()?);
    let (allowed, flag) = allow_plain;
    if !exposure.is_empty() {
        if !allowed {
            anyhow::bail!(
                "the lab's zenoh link {exposure}: anyone on that network could read or join it; use tls/ endpoints with mutual TLS or user/password in the zenoh config (docs/distributed.md), or {flag} on a closed network"
            );
        }
        tracing::warn!("the lab's zenoh link {exposure}: allowed by {flag} (a closed network only)");
    }
    Ok(settings)
}

impl LabJoinFlags {
    /// The robot's link to its lab, when `--lab` was given.
    pub fn link(
        self,
        store_dir: Option<&std::path::Path>,
    ) -> anyhow::Result<Option<subsume::lab::robot_link::RobotLinkOptions>> {
        use anyhow::Context as _;
        let Some(lab) = self.lab else { return Ok(None) };
        let secret = self
            .lab_secret
            .or_else(|| store_dir.map(|d| d.join("lab.secret")))
            .context("--lab needs the lab's secret: --lab-secret FILE")?;
        let key = subsume::lab::wire::LabKey::from_file(&lab, &secret)?;
        let allow = (self.lab_allow_plain, "--lab-allow-plain");
        let session = lab_session(self.lab_zenoh_config, &self.lab_connect, &self.lab_listen, allow)?;
        let robot = match self.lab_robot {
            Some(name) => name,
            None => std::fs::read_to_string("/proc/sys/kernel/hostname")
                .map(|h| h.trim().to_string())
                .context("cannot read the host name for the robot's name: give --lab-robot NAME")?,
        };
        Ok(Some(subsume::lab::robot_link::RobotLinkOptions {
            key,
            session,
            robot,
            lost_after: self.lab_lost,
            status_period: Duration::from_secs_f64(1.0 / self.lab_status_hz),
        }))
    }
}

/// `--lab-lost`: within the robot link's limits.
pub(super) fn lab_lost(text: &str) -> Result<Duration, String> {
    use subsume::lab::robot_link::{MAX_LOST_AFTER, MIN_LOST_AFTER};
    seconds_within(text, MIN_LOST_AFTER, MAX_LOST_AFTER)
}

/// `--lab-status-hz`: 0.1 to 10 per second.
pub(super) fn status_hz(text: &str) -> Result<f64, String> {
    match text.parse::<f64>() {
        Ok(hz) if hz.is_finite() && (0.1..=10.0).contains(&hz) => Ok(hz),
        _ => Err(format!("must be between 0.1 and 10 per second, got '{text}'")),
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

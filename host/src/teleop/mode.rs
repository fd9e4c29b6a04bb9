//! Control modes and the latency policy that permits them (the paper's
//! constraint module, MISSION M6/M7).
//!
//! - `direct`: the operator drives; network priority 1 + 0.
//! - `shared`: the operator's commands override the planner but not obstacle
//!   avoidance; priority 1 + 1.
//! - `supervisory`: the operator sets goals for the planner; their velocity
//!   commands only act while no autonomous behaviour is active; priority
//!   1 - 1.
//!
//! The measured round-trip time decides which modes a link allows: under
//! `direct_below` all three, under `shared_below` shared and supervisory,
//! otherwise supervisory only.

use std::fmt;
use std::time::Duration;

use serde::Serialize;

/// A control mode of a remote operator.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Mode {
    Supervisory,
    Shared,
    Direct,
}

impl Mode {
    pub const ALL: [Mode; 3] = [Mode::Direct, Mode::Shared, Mode::Supervisory];

    pub fn name(self) -> &'static str {
        match self {
            Mode::Direct => "direct",
            Mode::Shared => "shared",
            Mode::Supervisory => "supervisory",
        }
    }

    pub fn parse(name: &str) -> Option<Mode> {
        Mode::ALL.into_iter().find(|m| m.name().eq_ignore_ascii_case(name))
    }

    /// Offset added to the network source's base priority (M6).
    pub fn priority_offset(self) -> i32 {
        match self {
            Mode::Supervisory => -1,
            Mode::Direct => 0,
            Mode::Shared => 1,
        }
    }

    /// How much the mode lets the operator do, for picking the best allowed
    /// one: direct > shared > supervisory.
    fn capability(self) -> u8 {
        match self {
            Mode::Direct => 2,
            Mode::Shared => 1,
            Mode::Supervisory => 0,
        }
    }
}

impl fmt::Display for Mode {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// Which modes a round-trip time allows.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ModePolicy {
    /// Below this RTT every mode is allowed.
    pub direct_below: Duration,
    /// Below this RTT shared and supervisory are allowed; above, supervisory.
    pub shared_below: Duration,
}

impl Default for ModePolicy {
    fn default() -> Self {
        ModePolicy { direct_below: Duration::from_millis(100), shared_below: Duration::from_millis(300) }
    }
}

impl ModePolicy {
    /// The modes `rtt` allows, most capable first.
    pub fn allowed(&self, rtt: Duration) -> Vec<Mode> {
        if rtt < self.direct_below {
            vec![Mode::Direct, Mode::Shared, Mode::Supervisory]
        } else if rtt < self.shared_below {
            vec![Mode::Shared, Mode::Supervisory]
        } else {
            vec![Mode::Supervisory]
        }
    }

    /// The most capable mode `rtt` allows.
    pub fn best(&self, rtt: Duration) -> Mode {
        self.allowed(rtt).into_iter().max_by_key(|m| m.capability()).unwrap_or(Mode::Supervisory)
    }
}

/// "direct, shared, supervisory".
pub fn list(modes: &[Mode]) -> String {
    modes.iter().map(|m| m.name()).collect::<Vec<_>>().join(", ")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_rtt_decides_the_allowed_modes() {
        let policy = ModePolicy::default();
        let ms = Duration::from_millis;
        #[rustfmt::skip]
        let table = [
            (0,    vec![Mode::Direct, Mode::Shared, Mode::Supervisory], Mode::Direct),
            (99,   vec![Mode::Direct, Mode::Shared, Mode::Supervisory], Mode::Direct),
            (100,  vec![Mode::Shared, Mode::Supervisory],               Mode::Shared),
            (299,  vec![Mode::Shared, Mode::Supervisory],               Mode::Shared),
            (300,  vec![Mode::Supervisory],                             Mode::Supervisory),
            (5000, vec![Mode::Supervisory],                             Mode::Supervisory),
        ];
        for (rtt, allowed, best) in table {
            assert_eq!(policy.allowed(ms(rtt)), allowed, "{rtt} ms");
            assert_eq!(policy.best(ms(rtt)), best, "{rtt} ms");
        }
    }

    #[test]
    fn modes_shift_the_network_priority_as_the_paper_says() {
        assert_eq!([Mode::Supervisory, Mode::Direct, Mode::Shared].map(|m| 1 + m.priority_offset()), [0, 1, 2]);
        assert_eq!(Mode::parse("SHARED"), Some(Mode::Shared));
        assert_eq!(Mode::parse("manual"), None);
    }
}

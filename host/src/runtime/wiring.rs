//! How components are wired and kept alive: what a connection's mailbox
//! keeps ([`Policy`], [`Mailbox`]) and when a faulted component is brought
//! back ([`RestartPolicy`]). The robot file's validator produces these; the
//! graph consumes them.

use std::collections::VecDeque;

use crate::contract::Value;

/// How values wait at an input until the component handles them.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Policy {
    /// Only the newest value is kept.
    Latest,
    /// Up to `depth` values in order; when full the oldest is dropped (and
    /// counted).
    Queue { depth: usize },
}

/// What a connection does to a value on its way: the kinds of its two ends
/// decide (`contract::ValueKind::can_feed`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Convert {
    /// The value arrives as it was emitted.
    #[default]
    Nothing,
    /// A `scan` output into a `vector` input: the input receives the ranges
    /// (a built-in or a component that knows only vectors keeps working).
    ScanToRanges,
}

impl Convert {
    /// The conversion between an output of kind `from` and an input of
    /// kind `to`.
    pub fn between(from: crate::contract::ValueKind, to: crate::contract::ValueKind) -> Convert {
        use crate::contract::ValueKind;
        if from == ValueKind::Scan && to == ValueKind::Vector { Convert::ScanToRanges } else { Convert::Nothing }
    }

    /// `value` as the input receives it.
    pub fn apply(self, value: Value) -> Value {
        match (self, value) {
            (Convert::ScanToRanges, Value::Scan(scan)) => Value::Vector(scan.ranges),
            (_, value) => value,
        }
    }
}

/// When a faulted component is brought back.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct RestartPolicy {
    /// Restarts allowed over the run.
    pub max_restarts: u32,
    /// Wait before the first restart; doubled after each, up to
    /// [`MAX_RESTART_BACKOFF_NS`].
    pub backoff_ns: u64,
}

/// Longest wait between restarts: a component that keeps failing must not
/// cost the loop much, but must not wait for ever either.
pub const MAX_RESTART_BACKOFF_NS: u64 = 30_000_000_000;

/// The values waiting on one connection.
pub(crate) enum Mailbox {
    Latest(Option<Value>),
    Queue { values: VecDeque<Value>, depth: usize },
}

impl Mailbox {
    pub(crate) fn new(policy: Policy) -> Mailbox {
        match policy {
            Policy::Latest => Mailbox::Latest(None),
            Policy::Queue { depth } => Mailbox::Queue { values: VecDeque::with_capacity(depth), depth: depth.max(1) },
        }
    }
}

/// A motion source's current priority, shared with whoever may change it
/// (the network platform moves its own with the operator's mode; the
/// arbiter reads it at every decision).
#[derive(Clone, Debug, Default)]
pub struct PriorityCell(std::sync::Arc<std::sync::atomic::AtomicI32>);

impl PriorityCell {
    pub fn new(priority: i32) -> PriorityCell {
        PriorityCell(std::sync::Arc::new(std::sync::atomic::AtomicI32::new(priority)))
    }

    pub fn get(&self) -> i32 {
        self.0.load(std::sync::atomic::Ordering::Relaxed)
    }

    pub fn set(&self, priority: i32) {
        self.0.store(priority, std::sync::atomic::Ordering::Relaxed);
    }
}

impl PartialEq for PriorityCell {
    fn eq(&self, other: &Self) -> bool {
        self.get() == other.get()
    }
}

/// The name of the robot that runs now (the active set's robot file), for
/// whatever outlives one set (the network platform's `HELLO`). One per host;
/// whoever activates a set renames it.
#[derive(Debug, Default)]
pub struct RunningRobot(std::sync::RwLock<String>);

impl RunningRobot {
    pub fn new(name: &str) -> RunningRobot {
        RunningRobot(std::sync::RwLock::new(name.to_string()))
    }

    pub fn name(&self) -> String {
        self.0.read().map(|n| n.clone()).unwrap_or_default()
    }

    pub fn rename(&self, name: &str) {
        if let Ok(mut n) = self.0.write() {
            *n = name.to_string();
        }
    }
}

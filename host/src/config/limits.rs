//! Limits on what a robot file may ask for. Each answers a threat from a
//! careless or hostile file (uploaded files are validated with the same code).

use std::ops::RangeInclusive;
use std::time::Duration;

/// Largest robot file read: a huge file must not exhaust memory.
pub const MAX_CONFIG_BYTES: u64 = 1 << 20;
/// Most components in one robot: each gets a store, a memory and a slot in
/// the instance pool, which is sized for this many.
pub const MAX_COMPONENTS: usize = 64;
/// Most `<param>`s on one component.
pub const MAX_PARAMS_PER_COMPONENT: usize = 128;
/// Longest parameter value: values are copied into the guest at `init`.
pub const MAX_PARAM_VALUE_LEN: usize = 4096;
/// Fastest tick rate: a faster component would starve the control loop.
pub const MAX_RATE_HZ: f64 = 1000.0;
/// Tick rate when the file gives none.
pub const DEFAULT_RATE_HZ: f64 = 10.0;
/// Time budget per call. The floor is the epoch ticker's resolution; the
/// ceiling bounds how long one guest call can stall the control loop.
pub const CALL_BUDGET_RANGE: RangeInclusive<Duration> = Duration::from_millis(1)..=Duration::from_millis(1000);
/// Budget per call when the file gives none.
pub const DEFAULT_CALL_BUDGET: Duration = Duration::from_millis(10);
/// Linear memory per component. The floor fits a Rust guest's 1 MiB
/// stack; the ceiling is the instance pool's per-memory slot.
pub const MEMORY_RANGE: RangeInclusive<u64> = (2 << 20)..=(1 << 30);
/// Memory limit when the file gives none.
pub const DEFAULT_MEMORY_BYTES: u64 = 64 << 20;
/// Values one call may emit (`max-emits`): an emit flood must not fill
/// host memory or make the loop deliver for ever.
pub const EMITS_PER_CALL_RANGE: RangeInclusive<u32> = 1..=100_000;
pub const DEFAULT_EMITS_PER_CALL: u32 = 256;
/// Largest value one emit may carry, in bytes (`max-message`): one giant
/// value must not exhaust host memory (it is also the store's hostcall fuel).
pub const MESSAGE_BYTES_RANGE: RangeInclusive<u64> = (1 << 10)..=(16 << 20);
pub const DEFAULT_MESSAGE_BYTES: u64 = 1 << 20;
/// Log lines per second, `log` and stdout/stderr together (`max-logs`):
/// a guest must not flood the host's log.
pub const LOG_LINES_RANGE: RangeInclusive<u32> = 1..=10_000;
pub const DEFAULT_LOG_LINES_PER_S: u32 = 100;
/// Restarts after faults over a run (`max-restarts`, with
/// `restart="on-failure"`): a component that keeps failing must not keep
/// the host busy restarting it.
pub const MAX_RESTARTS_RANGE: RangeInclusive<u32> = 0..=100;
pub const DEFAULT_MAX_RESTARTS: u32 = 3;
/// Wait before the first restart; doubled after each.
pub const RESTART_BACKOFF: Duration = Duration::from_secs(1);
/// Deepest queue a connection may have: every queued value is held in
/// host memory.
pub const MAX_QUEUE_DEPTH: usize = 1024;
/// How long a motion source stays active after its last command. The
/// floor keeps a source from flickering; the ceiling bounds how long a
/// silent source can keep the robot moving on its last command.
pub const SOURCE_TIMEOUT_RANGE: RangeInclusive<Duration> = Duration::from_millis(10)..=Duration::from_secs(10);
/// Source timeout when the file gives none.
pub const DEFAULT_SOURCE_TIMEOUT: Duration = Duration::from_millis(500);
/// Queue depth for `policy="queue"` without `depth`.
pub const DEFAULT_QUEUE_DEPTH: usize = 16;
/// Allowed subsumption priorities.
pub const PRIORITY_RANGE: RangeInclusive<i32> = -1000..=1000;

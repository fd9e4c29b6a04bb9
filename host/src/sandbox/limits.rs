//! Every limit of the sandbox, each with the threat it answers: the engine's
//! (epoch tick, instance pool, stack), a store's (instances, tables,
//! memories, resource entries, handles) and a guest's text. The bottom of
//! the folder: it imports nothing of it.

use std::time::Duration;

/// How often the ticker thread advances the engine's epoch: the granularity
/// of the budget checks (`budget.rs`). A runaway call is stopped about one
/// tick after its CPU time reaches its budget (plus the ticker thread's
/// wake-up latency).
pub const EPOCH_TICK: Duration = Duration::from_millis(1);
/// Budget (CPU time) of `describe`: a component that loops there must not hang loading.
pub const DESCRIBE_BUDGET: Duration = Duration::from_millis(500);
/// Budget (CPU time) of instantiation plus `init`: a component that loops
/// while starting must not hang startup or activation.
pub const INIT_BUDGET: Duration = Duration::from_secs(1);
/// Memory given to the throwaway instance that answers `describe`.
pub const DESCRIBE_MEMORY_BYTES: u64 = 64 << 20;
/// Native stack a guest may use; deep recursion traps instead of crashing
/// the host.
pub const MAX_WASM_STACK_BYTES: usize = 512 << 10;
/// Core instances one component may create (componentize-py components
/// create about 38): bounds what one component takes from the pool.
pub const MAX_INSTANCES_PER_STORE: usize = 64;
/// Tables and memories one component may create.
pub const MAX_TABLES_PER_STORE: usize = 64;
pub const MAX_MEMORIES_PER_STORE: usize = 64;
/// Largest linear memory the instance pool reserves a slot for; per-component
/// limits from the robot file are at most this.
pub const POOL_MAX_MEMORY_BYTES: u64 = 1 << 30;
/// Core instances (and memories) the whole pool holds: enough for
/// [`MAX_COMPONENTS`](crate::config::limits::MAX_COMPONENTS) components plus throwaway `describe` instances.
pub const POOL_TOTAL_CORE_INSTANCES: u32 = 1000;

/// Entries a guest may hold in its WASI resource table (open streams,
/// pollables): a guest must not grow host-side tables without bound.
pub const MAX_RESOURCE_ENTRIES: usize = 1000;
/// Component-model handles alive at once in one store (`resource.new`).
pub const MAX_COMPONENT_HANDLES: usize = 1000;
/// Hostcall fuel beyond the component's `max-message`: room for the other
/// arguments of a host call.
pub const HOSTCALL_FUEL_SLACK: u64 = 64 << 10;
/// Longest message from a guest's `log` or `err` result kept in the log.
pub const MAX_GUEST_MESSAGE_BYTES: usize = 1024;

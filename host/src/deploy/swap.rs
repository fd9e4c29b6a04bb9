//! The control thread's side of an activation: a new graph waits in the
//! [`SwapSlot`] until [`ControlHook`] takes it between two cycles, moves
//! the carried components in and hands the old graph back; the hook also
//! publishes the live status while someone watches, and samples it into
//! the plots' history once a second whether or not anyone watches.

use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::mpsc::{Receiver, SyncSender};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use super::DeployError;
use super::history::{Observation, PlotHistory};
use crate::config::RobotConfig;
use crate::report::{self, ExperimentTag, LiveStatus};
use crate::runtime::Graph;
use crate::runtime::control_loop::{CycleHook, Waker};

/// Longest wait for the control loop to take a new graph: a loop stuck in a
/// call is bounded by the call's budget, so this only fires if it is gone.
pub const SWAP_TIMEOUT: Duration = Duration::from_secs(5);
/// How often the live status is published while someone watches.
pub const LIVE_PERIOD: Duration = Duration::from_millis(200);

/// A graph waiting for the control thread.
pub(super) struct SwapRequest {
    pub graph: Graph,
    /// (old index, new index) of carried components.
    pub carry: Vec<(usize, usize)>,
    pub config: Arc<RobotConfig>,
    pub set_id: u64,
    /// The experiment the new graph runs as, if any.
    pub experiment: Option<Arc<ExperimentTag>>,
    pub done: SyncSender<Graph>,
    /// Report the old graph (as stopped by, having run ns) before the swap.
    pub report: Option<ReportRequest>,
}

/// How long the old graph ran (ns), and where its report goes.
pub(super) type ReportRequest = (u64, SyncSender<report::Report>);

#[derive(Clone, Default)]
pub(super) struct SwapSlot {
    request: Arc<Mutex<Option<SwapRequest>>>,
    waiting: Arc<AtomicBool>,
    /// Graphs the control thread swapped in so far.
    swaps: Arc<AtomicU64>,
}

impl SwapSlot {
    /// Graphs the control thread swapped in so far.
    pub(super) fn swaps(&self) -> u64 {
        self.swaps.load(Ordering::Acquire)
    }

    /// Gives `request` to the control thread and waits for the old graph,
    /// which is dropped here (not on the loop).
    pub(super) fn hand_over(
        &self,
        request: SwapRequest,
        old_graph: &Receiver<Graph>,
        waker: &Waker,
    ) -> Result<(), DeployError> {
        {
            let mut slot = self.request.lock().map_err(|_| DeployError::Host("the swap slot is unusable".into()))?;
            *slot = Some(request);
        }
        self.waiting.store(true, Ordering::Release);
        waker.wake();
        match old_graph.recv_timeout(SWAP_TIMEOUT) {
            Ok(old) => {
                drop(old);
                Ok(())
            }
            Err(_) => {
                let taken_back = self.request.lock().ok().and_then(|mut slot| slot.take());
                if taken_back.is_some() {
                    return Err(DeployError::Host(format!(
                        "the control loop did not reach a cycle boundary within {} s",
                        SWAP_TIMEOUT.as_secs()
                    )));
                }
                // It was taken just now: the swap happened.
                drop(old_graph.recv_timeout(SWAP_TIMEOUT));
                Ok(())
            }
        }
    }
}

/// The live status as last published (`None` before the first), and
/// whether anyone watches.
#[derive(Clone)]
pub struct LiveStatusCell {
    sender: Arc<tokio::sync::watch::Sender<Arc<Option<LiveStatus>>>>,
}

impl Default for LiveStatusCell {
    fn default() -> Self {
        LiveStatusCell { sender: Arc::new(tokio::sync::watch::channel(Arc::new(None)).0) }
    }
}

impl LiveStatusCell {
    /// A receiver: while one exists, the control loop publishes.
    pub fn subscribe(&self) -> tokio::sync::watch::Receiver<Arc<Option<LiveStatus>>> {
        self.sender.subscribe()
    }
}

/// Runs on the control thread between cycles: swaps graphs, publishes the
/// live status.
pub struct ControlHook {
    slot: SwapSlot,
    config: Arc<RobotConfig>,
    set_id: u64,
    experiment: Option<Arc<ExperimentTag>>,
    live: LiveStatusCell,
    next_live_ns: u64,
    history: PlotHistory,
}

impl ControlHook {
    pub(super) fn new(
        slot: SwapSlot,
        config: Arc<RobotConfig>,
        set_id: u64,
        live: LiveStatusCell,
        history: PlotHistory,
    ) -> ControlHook {
        ControlHook { slot, config, set_id, experiment: None, live, next_live_ns: 0, history }
    }

    /// The robot running now (for the final report).
    pub fn config(&self) -> &Arc<RobotConfig> {
        &self.config
    }

    /// Graphs this hook swapped in so far (a recording from a fresh start
    /// attaches to the next).
    pub fn swaps(&self) -> u64 {
        self.slot.swaps()
    }
}

impl CycleHook for ControlHook {
    fn between_cycles(&mut self, graph: &mut Graph, now_ns: u64) {
        if self.slot.waiting.load(Ordering::Acquire) {
            self.slot.waiting.store(false, Ordering::Release);
            let request = self.slot.request.lock().ok().and_then(|mut slot| slot.take());
            if let Some(mut request) = request {
                if let Some((ran_ns, to)) = request.report.take() {
                    let _ = to.try_send(report::build_experiment(&self.config, graph, ran_ns as f64 / 1e9));
                }
                for &(old, new) in &request.carry {
                    if let Some(component) = graph.take_component(old) {
                        request.graph.replace_component(new, component);
                    }
                }
                std::mem::swap(graph, &mut request.graph);
                self.config = request.config;
                self.set_id = request.set_id;
                self.experiment = request.experiment;
                self.next_live_ns = now_ns;
                self.slot.swaps.fetch_add(1, Ordering::AcqRel);
                // The activating thread drops the old graph.
                let _ = request.done.try_send(request.graph);
            }
        }
        let mut published = None;
        if now_ns >= self.next_live_ns && self.live.sender.receiver_count() > 0 {
            self.next_live_ns = now_ns + LIVE_PERIOD.as_nanos() as u64;
            let status = Arc::new(Some(report::live(
                &self.config,
                graph,
                self.set_id,
                self.experiment.as_ref(),
                now_ns as f64 / 1e9,
            )));
            published = Some(status.clone());
            self.live.sender.send_replace(status);
        }
        let (config, set_id, experiment) = (&self.config, self.set_id, self.experiment.as_ref());
        self.history.sample_if_due(now_ns, || match published.as_deref() {
            Some(Some(status)) => Observation::of(status, now_ns),
            _ => Observation::of(&report::live(config, graph, set_id, experiment, now_ns as f64 / 1e9), now_ns),
        });
    }
}

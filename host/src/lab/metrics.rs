//! What `/metrics` shows of the lab: experiments by state, the queue's
//! length, the preflights' durations, and on a lab server its link's
//! counters.

use std::collections::BTreeMap;

use super::{Lab, server};
use crate::store::experiments::ExperimentState;

impl Lab {
    /// Counts of experiments by state, the queue's length, and the
    /// preflights' durations (for /metrics).
    pub fn metrics(&self) -> LabMetrics {
        let Ok(book) = self.book.lock() else { return LabMetrics::default() };
        let mut by_state = BTreeMap::new();
        for state in ExperimentState::ALL {
            by_state.insert(state.name(), 0);
        }
        let mut preflight_s = Vec::new();
        for record in book.experiments.values() {
            *by_state.entry(record.state.name()).or_default() += 1;
            if let Some(p) = &record.preflight {
                preflight_s.push(p.wall_s);
            }
        }
        let link = self.fleet().map(|fleet| fleet.link_figures());
        LabMetrics {
            by_state,
            queued: book.experiments.values().filter(|r| r.state == ExperimentState::Queued).count() as u64,
            preflight_wall_s: preflight_s,
            link,
            last_self_test: book.lab.self_tests.last().map(|t| t.passed),
            in_maintenance: book.lab.maintenance.is_some(),
        }
    }
}

/// What /metrics shows of the lab.
#[derive(Clone, Debug, Default)]
pub struct LabMetrics {
    pub by_state: BTreeMap<&'static str, u64>,
    pub queued: u64,
    pub preflight_wall_s: Vec<f64>,
    /// A lab server's link to its robots.
    pub link: Option<server::LinkFigures>,
    /// Whether the newest self-test passed (none run: absent).
    pub last_self_test: Option<bool>,
    /// The robot is out of service.
    pub in_maintenance: bool,
}

/// The bounds (seconds) of the preflight-duration histogram's buckets.
pub const PREFLIGHT_BUCKETS_S: [f64; 10] = [0.5, 1.0, 2.0, 5.0, 10.0, 20.0, 30.0, 60.0, 120.0, 300.0];

impl LabMetrics {
    /// The lab's metric families: experiments by state, the queue's
    /// length, the preflights' wall-clock durations.
    pub fn families(&self) -> Vec<crate::runtime::Family> {
        use crate::runtime::{Family, MetricKind, Sample};
        let mut states =
            Family::new("subsume_experiments", "experiments the lab keeps, by state (docs/lab.md)", MetricKind::Gauge);
        for (state, count) in &self.by_state {
            states.samples.push((vec![("state", (*state).to_string())], Sample::Gauge(*count as f64)));
        }
        let mut queue =
            Family::new("subsume_experiment_queue_length", "experiments queued for the robot", MetricKind::Gauge);
        queue.samples.push((vec![], Sample::Gauge(self.queued as f64)));
        let mut self_test = Family::new(
            "subsume_lab_self_test_passed",
            "1 if the robot's newest self-test passed, 0 if it failed (docs/lab.md, Self-test)",
            MetricKind::Gauge,
        );
        if let Some(passed) = self.last_self_test {
            self_test.samples.push((vec![], Sample::Gauge(if passed { 1.0 } else { 0.0 })));
        }
        let mut maintenance =
            Family::new("subsume_lab_maintenance", "1 while the robot is out of service", MetricKind::Gauge);
        maintenance.samples.push((vec![], Sample::Gauge(if self.in_maintenance { 1.0 } else { 0.0 })));
        let mut preflight = Family::new(
            "subsume_preflight_seconds",
            "wall-clock time of each preflight (the experiment in the simulator)",
            MetricKind::Histogram,
        );
        let mut buckets: Vec<(f64, u64)> = PREFLIGHT_BUCKETS_S.iter().map(|b| (*b, 0)).collect();
        buckets.push((f64::INFINITY, 0));
        for seconds in &self.preflight_wall_s {
            if let Some(bucket) = buckets.iter_mut().find(|(bound, _)| seconds <= bound) {
                bucket.1 += 1;
            }
        }
        let sum = self.preflight_wall_s.iter().sum();
        let count = self.preflight_wall_s.len() as u64;
        preflight.samples.push((vec![], Sample::Buckets { buckets, sum, count }));
        let mut families = vec![states, queue, preflight, self_test, maintenance];
        if let Some(link) = &self.link {
            families.push(
                Family::new(
                    "subsume_lab_robots",
                    "robots the lab server knows, by whether they are online (a token and fresh signed statuses)",
                    MetricKind::Gauge,
                )
                .gauge(vec![("online", "true".into())], link.online as f64)
                .gauge(vec![("online", "false".into())], (link.known - link.online) as f64),
            );
            families.push(
                Family::new(
                    "subsume_lab_statuses",
                    "robot statuses the lab server received and accepted",
                    MetricKind::Counter,
                )
                .counter(vec![], link.statuses),
            );
            families.push(
                Family::new(
                    "subsume_lab_tokens",
                    "robot token changes the lab server received and accepted",
                    MetricKind::Counter,
                )
                .counter(vec![], link.tokens),
            );
            families.push(
                Family::new(
                    "subsume_lab_foreign_messages",
                    "tokens and statuses not signed with this lab's key, ignored",
                    MetricKind::Counter,
                )
                .counter(vec![], link.foreign),
            );
            families.extend(link.refusal_families());
        }
        families
    }
}

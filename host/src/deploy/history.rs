//! The history behind the portal's plots, kept on the host: a sample of the
//! live status every [`HISTORY_PERIOD_NS`] of graph time (round-trip time
//! per operator, messages out per second per component, the arbiter's
//! holder), the last [`HISTORY_SAMPLES`] of them, so a page opened now
//! plots the last minutes at once (`GET /api/v1/history`) and then goes on
//! with the live events.
//!
//! Invariants: the control thread never waits for a reader (it takes the
//! ring with `try_lock` and, if a reader holds it, samples a cycle later);
//! the ring holds at most [`HISTORY_SAMPLES`]; sample times increase; a
//! rate is only computed between two samples of the same set (counters
//! start again with each activation).

use std::collections::{BTreeMap, HashMap, VecDeque};
use std::sync::{Arc, Mutex};

use serde::Serialize;

use crate::arbiter::ArbiterStatus;
use crate::report::LiveStatus;
use crate::teleop::TeleopStatus;

/// Graph time between two samples. The plots need no finer grain, and
/// each sample costs the control thread one live status.
pub const HISTORY_PERIOD_NS: u64 = 1_000_000_000;
/// Samples kept: 300 s at one a second, the page's plot window. A host
/// running for days keeps no more, and a page reading the history gets an
/// answer of bounded size.
pub const HISTORY_SAMPLES: usize = 300;
/// Operators and components a sample names at most: a robot file or a
/// crowd of operators cannot grow a sample (and the answer) without bound.
pub const MAX_SAMPLE_SERIES: usize = 64;

/// One sample, as `GET /api/v1/history` answers it.
#[derive(Clone, Debug, PartialEq, Serialize, schemars::JsonSchema)]
pub struct HistorySample {
    /// Graph time, seconds since the host started.
    pub t_s: f64,
    /// The active set.
    pub set: u64,
    /// The experiment it runs as, and its submitter, if any.
    pub experiment: Option<(u64, String)>,
    /// Round-trip time of each connected operator, milliseconds.
    pub rtt_ms: BTreeMap<String, f64>,
    /// Messages each component emitted per second since the sample before
    /// (none in the first sample of a set).
    pub rates: BTreeMap<String, f64>,
    /// Who holds control: the arbiter's holder, `STOP` when nobody, `no
    /// arbiter` for a set without one.
    pub holder: String,
}

/// What a sample is made of: what the live status says at `t_ns`.
#[derive(Clone, Debug, PartialEq)]
pub struct Observation {
    pub t_ns: u64,
    pub set: u64,
    pub experiment: Option<(u64, String)>,
    pub rtt_ms: Vec<(String, f64)>,
    /// Messages out so far, per component.
    pub messages_out: Vec<(String, u64)>,
    pub holder: String,
}

impl Observation {
    /// The observation in a live status published at graph time `t_ns`.
    pub fn of(status: &LiveStatus, t_ns: u64) -> Observation {
        let sections = &status.report.sections;
        let rtt_ms = sections
            .of::<TeleopStatus>()
            .flat_map(|(_, teleop)| teleop.open_sessions())
            .filter_map(|s| Some((s.operator.clone()?, s.rtt_ms?)))
            .take(MAX_SAMPLE_SERIES)
            .collect();
        let messages_out =
            status.report.components.iter().take(MAX_SAMPLE_SERIES).map(|c| (c.name.clone(), c.messages_out)).collect();
        let holder = match sections.of::<ArbiterStatus>().next() {
            None => "no arbiter".to_string(),
            Some((_, arbiter)) => match &arbiter.holder {
                Some(holder) if !holder.is_empty() => holder.clone(),
                _ => "STOP".to_string(),
            },
        };
        let experiment = status.experiment.as_ref().map(|e| (e.id, e.submitter.clone()));
        Observation { t_ns, set: status.set, experiment, rtt_ms, messages_out, holder }
    }
}

#[derive(Default)]
struct Ring {
    samples: VecDeque<HistorySample>,
    /// The counters of the last sample: (set, time, messages out).
    last: Option<(u64, u64, HashMap<String, u64>)>,
    /// Graph time of the next sample.
    next_ns: u64,
}

/// The host's plot history: written by the control thread, read by the
/// portal.
#[derive(Clone, Default)]
pub struct PlotHistory {
    ring: Arc<Mutex<Ring>>,
}

impl PlotHistory {
    /// Takes a sample (`observe` makes it) if one is due at `now_ns`: on
    /// the [`HISTORY_PERIOD_NS`] grid, the first at the first call. Never
    /// waits: with a reader holding the ring, the sample is taken on a
    /// later call.
    pub fn sample_if_due(&self, now_ns: u64, observe: impl FnOnce() -> Observation) {
        let Ok(mut ring) = self.ring.try_lock() else { return };
        if now_ns < ring.next_ns {
            return;
        }
        ring.next_ns = (now_ns / HISTORY_PERIOD_NS + 1) * HISTORY_PERIOD_NS;
        let seen = observe();
        let counts: HashMap<String, u64> = seen.messages_out.iter().cloned().collect();
        let mut rates = BTreeMap::new();
        if let Some((set, t_ns, before)) = &ring.last
            && *set == seen.set
            && seen.t_ns > *t_ns
        {
            let dt = (seen.t_ns - t_ns) as f64 / 1e9;
            for (name, out) in &seen.messages_out {
                if let Some(&earlier) = before.get(name)
                    && *out >= earlier
                {
                    rates.insert(name.clone(), (out - earlier) as f64 / dt);
                }
            }
        }
        let sample = HistorySample {
            t_s: seen.t_ns as f64 / 1e9,
            set: seen.set,
            experiment: seen.experiment,
            rtt_ms: seen.rtt_ms.into_iter().collect(),
            rates,
            holder: seen.holder,
        };
        ring.last = Some((seen.set, seen.t_ns, counts));
        if ring.samples.len() >= HISTORY_SAMPLES {
            ring.samples.pop_front();
        }
        ring.samples.push_back(sample);
    }

    /// The samples kept, oldest first.
    pub fn samples(&self) -> Vec<HistorySample> {
        self.ring.lock().map(|ring| ring.samples.iter().cloned().collect()).unwrap_or_default()
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]

    use super::*;

    fn seen(t_s: u64, set: u64, motors: u64, holder: &str) -> Observation {
        Observation {
            t_ns: t_s * 1_000_000_000 + 3_000_000,
            set,
            experiment: None,
            rtt_ms: vec![("ada".into(), 12.5)],
            messages_out: vec![("motors".into(), motors), ("planner".into(), motors / 10)],
            holder: holder.into(),
        }
    }

    /// Controlled time: cycles every 10 ms for 20 minutes of graph time.
    /// One sample a second, at most HISTORY_SAMPLES kept, times increasing,
    /// rates from the counters, none across an activation.
    #[test]
    fn one_sample_a_second_the_last_five_minutes_with_rates_from_the_counters() {
        let history = PlotHistory::default();
        let mut calls = 0;
        for cycle in 0..120_000u64 {
            let now_ns = cycle * 10_000_000;
            let t_s = now_ns / 1_000_000_000;
            // Set 2 from 1000 s on; the motors emit 200 a second.
            let set = if t_s < 1000 { 1 } else { 2 };
            history.sample_if_due(now_ns, || {
                calls += 1;
                let mut observed =
                    seen(t_s, set, (t_s % 1000) * 200, if t_s.is_multiple_of(2) { "planner" } else { "STOP" });
                observed.t_ns = now_ns;
                observed
            });
            if cycle == 50 {
                assert_eq!(history.samples().len(), 1, "the first call samples, then once a second");
            }
        }
        assert_eq!(calls, 1200, "one observation a second, not one a cycle");
        let samples = history.samples();
        assert_eq!(samples.len(), HISTORY_SAMPLES);
        assert_eq!(samples.first().unwrap().t_s, 900.0);
        assert_eq!(samples.last().unwrap().t_s, 1199.0);
        assert!(samples.windows(2).all(|w| w[1].t_s > w[0].t_s));
        for sample in &samples {
            assert_eq!(sample.rtt_ms, BTreeMap::from([("ada".to_string(), 12.5)]));
            assert_eq!(sample.holder, if (sample.t_s as u64).is_multiple_of(2) { "planner" } else { "STOP" });
            if sample.t_s == 1000.0 {
                assert!(sample.rates.is_empty(), "a rate across an activation: {sample:?}");
            } else {
                assert_eq!(sample.rates["motors"], 200.0, "{sample:?}");
                assert_eq!(sample.rates["planner"], 20.0, "{sample:?}");
            }
        }
    }

    /// A reader holding the ring delays a sample; the control thread does
    /// not wait for it.
    #[test]
    fn a_reader_holding_the_ring_delays_the_sample_and_never_blocks() {
        let history = PlotHistory::default();
        let held = history.ring.lock().unwrap();
        history.sample_if_due(0, || seen(0, 1, 0, "STOP"));
        drop(held);
        assert!(history.samples().is_empty());
        history.sample_if_due(10_000_000, || seen(0, 1, 0, "STOP"));
        assert_eq!(history.samples().len(), 1);
    }
}

//! The host's health as Prometheus metrics: the live status (`report`) of
//! the running set, turned into metric families and written in the
//! OpenMetrics text format by the `prometheus-client` crate. The portal
//! serves it at `/metrics` (docs/service.md says who may read it).
//!
//! Nothing here runs on the control loop: counters are the ones the graph
//! and the built-ins keep anyway (plain integers on the control thread,
//! atomics on I/O threads), and the two histograms (call time, loop
//! lateness) are fixed-bucket counts the graph keeps
//! (`runtime::Histogram`). A scrape asks for a fresh live status, as the
//! portal's live view does, and encodes it on the portal's runtime.

use prometheus_client::collector::Collector;
use prometheus_client::encoding::{DescriptorEncoder, MetricEncoder, NoLabelSet};
use prometheus_client::metrics::MetricType;
use prometheus_client::registry::Registry;
use serde_json::Value as Json;

use crate::report::{LiveStatus, Report};
use crate::runtime::Histogram;

/// The content type of [`encode`]'s text.
pub const CONTENT_TYPE: &str = "application/openmetrics-text; version=1.0.0; charset=utf-8";

/// One sample's value.
#[derive(Clone, Debug)]
pub enum Sample {
    Counter(u64),
    Gauge(f64),
    Histogram(Histogram),
    /// A histogram with buckets of its own: (upper bound in seconds, count
    /// in that bucket alone; the last bound infinity), sum, count.
    Buckets {
        buckets: Vec<(f64, u64)>,
        sum: f64,
        count: u64,
    },
}

/// A metric family: its name (counters without `_total`, which the encoder
/// adds), help, type and labelled samples.
#[derive(Clone, Debug)]
pub struct Family {
    pub name: &'static str,
    pub help: &'static str,
    pub kind: MetricType,
    pub samples: Vec<(Vec<(&'static str, String)>, Sample)>,
}

impl Family {
    pub fn new(name: &'static str, help: &'static str, kind: MetricType) -> Family {
        Family { name, help, kind, samples: Vec::new() }
    }

    pub fn counter(&mut self, labels: Vec<(&'static str, String)>, value: u64) {
        self.samples.push((labels, Sample::Counter(value)));
    }
}

/// The metric families of a live status.
pub fn families(status: &LiveStatus) -> Vec<Family> {
    let report = &status.report;
    let mut out = Vec::new();
    let mut set = Family::new("subsume_active_set", "the id of the running set", MetricType::Gauge);
    set.samples.push((vec![("robot", report.robot.clone())], Sample::Gauge(status.set as f64)));
    out.push(set);
    let mut cycles =
        Family::new("subsume_loop_cycles", "control-loop cycles run by the running set", MetricType::Counter);
    cycles.counter(vec![], report.cycles);
    out.push(cycles);
    let mut lateness = Family::new(
        "subsume_loop_lateness_seconds",
        "how long after its time the control loop ran each scheduled cycle",
        MetricType::Histogram,
    );
    lateness.samples.push((vec![], Sample::Histogram(report.loop_lateness.histogram.clone())));
    out.push(lateness);
    out.extend(component_families(report));
    out.extend(section_families(report));
    out
}

fn component_families(report: &Report) -> Vec<Family> {
    use MetricType::{Counter, Gauge, Histogram};
    let mut calls = Family::new("subsume_component_calls", "calls of tick and on-input", Counter);
    let mut call_time = Family::new(
        "subsume_component_call_seconds",
        "time of each call, with the routing of what it emitted",
        Histogram,
    );
    let mut faults = Family::new("subsume_component_faults", "times a component was faulted", Counter);
    let mut restarts = Family::new("subsume_component_restarts", "restarts after faults", Counter);
    let mut running = Family::new("subsume_component_running", "1 while the component runs, 0 once faulted", Gauge);
    let mut messages_in = Family::new("subsume_component_messages_in", "values handed to on-input", Counter);
    let mut messages_out = Family::new("subsume_component_messages_out", "values emitted", Counter);
    let mut dropped =
        Family::new("subsume_component_messages_dropped", "values dropped from full queues feeding it", Counter);
    let mut missed =
        Family::new("subsume_component_missed_ticks", "ticks skipped because the loop fell behind", Counter);
    for c in &report.components {
        let labels = || vec![("component", c.name.clone()), ("platform", c.platform.clone())];
        calls.counter(labels(), c.calls);
        call_time.samples.push((labels(), Sample::Histogram(c.call_times.clone())));
        faults.counter(labels(), c.faults);
        restarts.counter(labels(), c.restarts);
        running.samples.push((labels(), Sample::Gauge(if c.state == "running" { 1.0 } else { 0.0 })));
        messages_in.counter(labels(), c.messages_in);
        messages_out.counter(labels(), c.messages_out);
        dropped.counter(labels(), c.messages_dropped);
        missed.counter(labels(), c.missed_ticks);
    }
    vec![calls, call_time, faults, restarts, running, messages_in, messages_out, dropped, missed]
}

/// The sections `builtin:KIND` components add to the report
/// (docs/report.md) under `section` (`section:NAME` when the kind appears
/// twice), with the name of the component each belongs to.
fn sections<'a>(report: &'a Report, section: &str, kind: &str) -> Vec<(String, &'a Json)> {
    report
        .sections
        .iter()
        .filter_map(|(key, value)| {
            let (section_kind, name) = match key.split_once(':') {
                Some((k, name)) => (k, Some(name.to_string())),
                None => (key.as_str(), None),
            };
            (section_kind == section).then(|| {
                let name = name.or_else(|| {
                    let source = format!("builtin:{kind}");
                    report.components.iter().find(|c| c.source == source).map(|c| c.name.clone())
                });
                (name.unwrap_or_else(|| kind.to_string()), value)
            })
        })
        .collect()
}

fn count(value: &Json, field: &str) -> u64 {
    value.get(field).and_then(Json::as_u64).unwrap_or(0)
}

fn section_families(report: &Report) -> Vec<Family> {
    use MetricType::{Counter, Gauge};
    let mut switches =
        Family::new("subsume_arbiter_switches", "changes of the source holding control (to and from none)", Counter);
    let mut stops = Family::new("subsume_arbiter_stops", "STOP commands sent because no source was active", Counter);
    for (name, value) in sections(report, "arbiter", "arbiter") {
        switches.counter(vec![("arbiter", name.clone())], count(value, "switches"));
        stops.counter(vec![("arbiter", name)], count(value, "stops_sent"));
    }
    let mut frames = Family::new("subsume_serial_frames", "frames written to the motor controller", Counter);
    let mut malformed =
        Family::new("subsume_serial_malformed_feedback", "feedback from the controller that did not parse", Counter);
    let mut reconnects = Family::new("subsume_serial_reconnects", "times the serial device was opened again", Counter);
    let mut connected = Family::new("subsume_serial_connected", "1 while the serial device is open", Gauge);
    let mut watchdog =
        Family::new("subsume_serial_watchdog_stops", "STOPs sent because commands stopped coming", Counter);
    for (name, value) in sections(report, "serial", "serial") {
        let labels = || vec![("link", name.clone())];
        frames.counter(labels(), count(value, "frames_written"));
        malformed.counter(labels(), count(value, "malformed_feedback"));
        reconnects.counter(labels(), count(value, "reconnects"));
        watchdog.counter(labels(), count(value, "watchdog_stops"));
        let open = value.get("connected").and_then(Json::as_bool).unwrap_or(false);
        connected.samples.push((labels(), Sample::Gauge(if open { 1.0 } else { 0.0 })));
    }
    let mut rtt = Family::new(
        "subsume_teleop_rtt_seconds",
        "the last measured round-trip time of each connected operator session",
        Gauge,
    );
    let mut sessions = Family::new("subsume_teleop_sessions", "operator connections open now", Gauge);
    let mut released =
        Family::new("subsume_teleop_commands_released", "operator commands released by the delay buffer", Counter);
    let mut dropped = Family::new(
        "subsume_teleop_commands_dropped",
        "operator commands never released, by reason (stale, duplicate, full, superseded)",
        Counter,
    );
    for (name, value) in sections(report, "network", "teleop") {
        let mut open = 0u64;
        for session in value.get("sessions").and_then(Json::as_array).into_iter().flatten() {
            if !session.get("disconnected_at_s").is_none_or(Json::is_null) {
                continue;
            }
            open += 1;
            if let Some(ms) = session.get("rtt_ms").and_then(Json::as_f64) {
                let operator = session.get("operator").and_then(Json::as_str).unwrap_or("").to_string();
                let labels = vec![
                    ("network", name.clone()),
                    ("session", count(session, "session").to_string()),
                    ("operator", operator),
                ];
                rtt.samples.push((labels, Sample::Gauge(ms / 1e3)));
            }
        }
        sessions.samples.push((vec![("network", name.clone())], Sample::Gauge(open as f64)));
        let commands = value.get("commands").unwrap_or(&Json::Null);
        released.counter(vec![("network", name.clone())], count(commands, "released"));
        for (reason, field) in [
            ("stale", "dropped_stale"),
            ("duplicate", "dropped_duplicate"),
            ("full", "dropped_full"),
            ("superseded", "superseded"),
        ] {
            dropped.counter(vec![("network", name.clone()), ("reason", reason.to_string())], count(commands, field));
        }
    }
    vec![switches, stops, frames, malformed, reconnects, connected, watchdog, rtt, sessions, released, dropped]
}

/// Encodes the families of one scrape.
#[derive(Debug)]
struct Scrape(Vec<Family>);

impl Collector for Scrape {
    fn encode(&self, mut encoder: DescriptorEncoder<'_>) -> Result<(), std::fmt::Error> {
        for family in &self.0 {
            let mut metric = encoder.encode_descriptor(family.name, family.help, None, family.kind)?;
            for (labels, sample) in &family.samples {
                // No labels: the sample alone (`name 1`, not `name{} 1`).
                if labels.is_empty() {
                    encode_sample(&mut metric, sample)?;
                } else {
                    encode_sample(&mut metric.encode_family(labels)?, sample)?;
                }
            }
        }
        Ok(())
    }
}

fn encode_sample(encoder: &mut MetricEncoder<'_>, sample: &Sample) -> Result<(), std::fmt::Error> {
    match sample {
        Sample::Counter(value) => encoder.encode_counter::<NoLabelSet, _, u64>(value, None),
        Sample::Gauge(value) => encoder.encode_gauge(value),
        Sample::Histogram(h) => {
            encoder.encode_histogram::<NoLabelSet>(h.sum_ns() as f64 / 1e9, h.count(), &h.buckets_seconds(), None)
        }
        Sample::Buckets { buckets, sum, count } => encoder.encode_histogram::<NoLabelSet>(*sum, *count, buckets, None),
    }
}

/// The OpenMetrics text of `status` (ends with `# EOF`).
pub fn encode(status: &LiveStatus) -> String {
    encode_with(status, Vec::new())
}

/// [`encode`], with `more` families after the live status's (the lab's).
pub fn encode_with(status: &LiveStatus, more: Vec<Family>) -> String {
    let mut registry = Registry::default();
    let mut all = families(status);
    all.extend(more);
    registry.register_collector(Box::new(Scrape(all)));
    let mut text = String::new();
    // Writing to a String cannot fail; an encoder error would leave a
    // truncated text, which a scraper refuses as a whole.
    let _ = prometheus_client::encoding::text::encode(&mut text, &registry);
    text
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::report::{ComponentReport, LoopLateness, MessageTotals};

    fn status() -> LiveStatus {
        let mut call_times = Histogram::default();
        call_times.record(3_000);
        call_times.record(40_000);
        let mut lateness = Histogram::default();
        lateness.record(2_000_000_000);
        let component = ComponentReport {
            name: "avoid".into(),
            platform: "control".into(),
            source: "avoider.wasm".into(),
            rate_hz: 10.0,
            priority: Some(3),
            state: "faulted".into(),
            fault: Some("trap".into()),
            faulted_at_s: Some(1.0),
            calls: 2,
            ticks: 2,
            missed_ticks: 0,
            call_time_ms: 0.043,
            messages_in: 5,
            messages_out: 4,
            messages_dropped: 1,
            errors: 0,
            last_error: None,
            restarts: 0,
            faults: 1,
            call_times,
        };
        let mut arbiter = component.clone();
        arbiter.name = "arb".into();
        arbiter.source = "builtin:arbiter".into();
        let mut teleop = component.clone();
        teleop.name = "teleop".into();
        teleop.source = "builtin:teleop".into();
        let mut sections = serde_json::Map::new();
        sections.insert("arbiter".into(), serde_json::json!({ "switches": 3, "stops_sent": 7 }));
        sections.insert(
            "network".into(),
            serde_json::json!({
                "sessions": [
                    { "session": 1, "operator": "alice", "rtt_ms": 12.5, "disconnected_at_s": null },
                    { "session": 2, "operator": "bob", "rtt_ms": 80.0, "disconnected_at_s": 3.0 },
                ],
                "commands": { "released": 9, "dropped_stale": 2, "dropped_duplicate": 0, "dropped_full": 0, "superseded": 1 },
            }),
        );
        sections.insert("network:teleop2".into(), serde_json::json!({ "sessions": [], "commands": {} }));
        LiveStatus {
            experiment: None,
            live_format: 1,
            set: 4,
            report: Report {
                format: 1,
                robot: "demo".into(),
                config: "robot.xml".into(),
                stopped_by: "running".into(),
                duration_s: 1.0,
                cycles: 10,
                components: vec![component, arbiter, teleop],
                connections: vec![],
                messages: MessageTotals { routed: 0, delivered: 0, dropped: 0 },
                loop_lateness: LoopLateness {
                    cycles: 1,
                    total_ms: 2000.0,
                    max_ms: 2000.0,
                    waited_for_cpu_ms: 0.0,
                    histogram: lateness,
                },
                sections,
            },
        }
    }

    #[test]
    fn the_text_names_every_sample_with_its_labels() {
        let text = encode(&status());
        for line in [
            "# TYPE subsume_component_calls counter",
            "subsume_component_calls_total{component=\"avoid\",platform=\"control\"} 2",
            "subsume_component_faults_total{component=\"avoid\",platform=\"control\"} 1",
            "subsume_component_running{component=\"avoid\",platform=\"control\"} 0.0",
            "subsume_component_call_seconds_count{component=\"avoid\",platform=\"control\"} 2",
            "subsume_component_call_seconds_bucket{le=\"0.000004096\",component=\"avoid\",platform=\"control\"} 1",
            "subsume_component_call_seconds_bucket{le=\"+Inf\",component=\"avoid\",platform=\"control\"} 2",
            "subsume_loop_lateness_seconds_bucket{le=\"1.073741824\"} 0",
            "subsume_loop_lateness_seconds_bucket{le=\"+Inf\"} 1",
            "subsume_loop_lateness_seconds_sum 2.0",
            "subsume_arbiter_switches_total{arbiter=\"arb\"} 3",
            "subsume_arbiter_stops_total{arbiter=\"arb\"} 7",
            "subsume_teleop_rtt_seconds{network=\"teleop\",session=\"1\",operator=\"alice\"} 0.0125",
            "subsume_teleop_sessions{network=\"teleop\"} 1.0",
            "subsume_teleop_sessions{network=\"teleop2\"} 0.0",
            "subsume_teleop_commands_released_total{network=\"teleop\"} 9",
            "subsume_teleop_commands_dropped_total{network=\"teleop\",reason=\"stale\"} 2",
            "subsume_teleop_commands_dropped_total{network=\"teleop\",reason=\"superseded\"} 1",
            "subsume_active_set{robot=\"demo\"} 4.0",
            "subsume_loop_cycles_total 10",
        ] {
            assert!(text.lines().any(|l| l == line), "missing '{line}' in:\n{text}");
        }
        // A disconnected session has no round-trip time.
        assert!(!text.contains("bob"), "{text}");
        assert!(text.ends_with("# EOF\n"), "{text}");
    }
}

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

use crate::report::{ComponentRunState, LiveStatus, Report};
use crate::runtime::{Family, MetricKind, Sample};

/// The content type of [`encode`]'s text.
pub const CONTENT_TYPE: &str = "application/openmetrics-text; version=1.0.0; charset=utf-8";

/// The metric families of a live status.
pub fn families(status: &LiveStatus) -> Vec<Family> {
    let report = &status.report;
    let mut out = Vec::new();
    out.push(
        Family::new("subsume_active_set", "the id of the running set", MetricKind::Gauge)
            .gauge(vec![("robot", report.robot.clone())], status.set as f64),
    );
    out.push(
        Family::new("subsume_loop_cycles", "control-loop cycles run by the running set", MetricKind::Counter)
            .counter(vec![], report.cycles),
    );
    let mut lateness = Family::new(
        "subsume_loop_lateness_seconds",
        "how long after its time the control loop ran each scheduled cycle",
        MetricKind::Histogram,
    );
    lateness.samples.push((vec![], Sample::Histogram(report.loop_lateness.histogram.clone())));
    out.push(lateness);
    out.extend(component_families(report));
    out.extend(section_families(report));
    out
}

fn component_families(report: &Report) -> Vec<Family> {
    use MetricKind::{Counter, Gauge, Histogram};
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
        calls = calls.counter(labels(), c.calls);
        call_time.samples.push((labels(), Sample::Histogram(c.call_times.clone())));
        faults = faults.counter(labels(), c.faults);
        restarts = restarts.counter(labels(), c.restarts);
        let up = if c.state == ComponentRunState::Running { 1.0 } else { 0.0 };
        running = running.gauge(labels(), up);
        messages_in = messages_in.counter(labels(), c.messages_in);
        messages_out = messages_out.counter(labels(), c.messages_out);
        dropped = dropped.counter(labels(), c.messages_dropped);
        missed = missed.counter(labels(), c.missed_ticks);
    }
    vec![calls, call_time, faults, restarts, running, messages_in, messages_out, dropped, missed]
}

/// The families each built-in's section names, those of the same name
/// (two serial links) merged into one.
fn section_families(report: &Report) -> Vec<Family> {
    let mut merged: Vec<Family> = Vec::new();
    for section in &report.sections.0 {
        for family in section.status.metric_families(&section.component) {
            match merged.iter_mut().find(|f| f.name == family.name) {
                Some(known) => known.samples.extend(family.samples),
                None => merged.push(family),
            }
        }
    }
    merged
}

/// Encodes the families of one scrape.
#[derive(Debug)]
struct Scrape(Vec<Family>);

impl Collector for Scrape {
    fn encode(&self, mut encoder: DescriptorEncoder<'_>) -> Result<(), std::fmt::Error> {
        for family in &self.0 {
            let kind = match family.kind {
                MetricKind::Counter => MetricType::Counter,
                MetricKind::Gauge => MetricType::Gauge,
                MetricKind::Histogram => MetricType::Histogram,
            };
            let mut metric = encoder.encode_descriptor(family.name, family.help, None, kind)?;
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
    let mut all = families(status);
    all.extend(more);
    encode_families(all)
}

/// The OpenMetrics text of `all` (a lab server's, which runs no robot).
pub fn encode_families(all: Vec<Family>) -> String {
    let mut registry = Registry::default();
    registry.register_collector(Box::new(Scrape(all)));
    let mut text = String::new();
    // Writing to a String cannot fail; an encoder error would leave a
    // truncated text, which a scraper refuses as a whole.
    let _ = prometheus_client::encoding::text::encode(&mut text, &registry);
    text
}

#[cfg(test)]
mod tests {
    use std::sync::Arc;

    use super::*;
    use crate::arbiter::ArbiterStatus;
    use crate::report::{ComponentReport, LoopLateness, MessageTotals, Section, Sections, StoppedBy};
    use crate::robot::serial::SerialStatus;
    use crate::runtime::{Histogram, StatusSection};
    use crate::teleop::delay::DelayStats;
    use crate::teleop::{SessionReport, TeleopStatus};

    fn section(key: &str, component: &str, status: impl StatusSection) -> Section {
        Section { key: key.into(), component: component.into(), status: Arc::new(status) }
    }

    fn teleop() -> TeleopStatus {
        let session = |session: u64, operator: &str, rtt_ms: f64, disconnected_at_s: Option<f64>| SessionReport {
            session,
            operator: Some(operator.into()),
            rtt_ms: Some(rtt_ms),
            disconnected_at_s,
            ..SessionReport::default()
        };
        TeleopStatus {
            sessions: vec![session(1, "alice", 12.5, None), session(2, "bob", 80.0, Some(3.0))],
            commands: DelayStats { released: 9, dropped_stale: 2, superseded: 1, ..DelayStats::default() },
            ..TeleopStatus::default()
        }
    }

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
            state: ComponentRunState::Faulted,
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
        let arbiter = ArbiterStatus { switches: 3, stops_sent: 7, ..ArbiterStatus::default() };
        let sections = Sections(vec![
            section("arbiter", "arb", arbiter),
            section("teleop", "teleop", teleop()),
            section("teleop:teleop2", "teleop2", TeleopStatus::default()),
        ]);
        LiveStatus {
            experiment: None,
            live_format: 1,
            set: 4,
            report: Report {
                format: crate::report::REPORT_FORMAT,
                robot: "demo".into(),
                config: "robot.xml".into(),
                stopped_by: StoppedBy::Running,
                duration_s: 1.0,
                cycles: 10,
                components: vec![component],
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

    /// Each section's metric reads a field the report's JSON shows under
    /// this name: renaming or dropping the field (or feeding the metric
    /// from another) fails here.
    #[test]
    fn every_section_metric_is_the_field_the_report_shows() {
        let serial = SerialStatus {
            frames_written: 11,
            malformed_feedback: 12,
            reconnects: 13,
            watchdog_stops: 14,
            connected: true,
            ..SerialStatus::default()
        };
        let arbiter = ArbiterStatus { switches: 21, stops_sent: 22, ..ArbiterStatus::default() };
        // (a section, [(its metric family, the JSON field it shows)]).
        type Case = (Box<dyn StatusSection>, &'static [(&'static str, &'static str)]);
        let cases: Vec<Case> = vec![
            (Box::new(arbiter), &[("subsume_arbiter_switches", "/switches"), ("subsume_arbiter_stops", "/stops_sent")]),
            (
                Box::new(serial),
                &[
                    ("subsume_serial_frames", "/frames_written"),
                    ("subsume_serial_malformed_feedback", "/malformed_feedback"),
                    ("subsume_serial_reconnects", "/reconnects"),
                    ("subsume_serial_watchdog_stops", "/watchdog_stops"),
                    ("subsume_serial_connected", "/connected"),
                ],
            ),
            (
                Box::new(crate::camera::CameraSection {
                    source: "http",
                    url: Some("http://cam/".into()),
                    width: 320,
                    height: 240,
                    frames_made: 31,
                    frames_sent: 32,
                    frames_dropped: 33,
                    frames_late: 0,
                    encode_failures: 0,
                    busy_s: 0.5,
                    last_frame_age_s: 3.5,
                    stale: true,
                    frames_rejected: Some(34),
                    frames_skipped: Some(0),
                    stream_errors: Some(2),
                    reconnects: Some(35),
                    connected: Some(false),
                }),
                &[
                    ("subsume_camera_frames", "/frames_sent"),
                    ("subsume_camera_frames_dropped", "/frames_dropped"),
                    ("subsume_camera_frame_age_seconds", "/last_frame_age_s"),
                    ("subsume_camera_frames_rejected", "/frames_rejected"),
                    ("subsume_camera_reconnects", "/reconnects"),
                ],
            ),
            (
                Box::new(teleop()),
                &[
                    ("subsume_teleop_commands_released", "/commands/released"),
                    ("subsume_teleop_rtt_seconds", "/sessions/0/rtt_ms"),
                ],
            ),
        ];
        for (status, fields) in cases {
            let json = status.to_json();
            let families = status.metric_families("c");
            for (family, pointer) in fields {
                let shown = json.pointer(pointer).unwrap_or_else(|| panic!("{} has no {pointer}", status.section()));
                let shown = shown.as_f64().or_else(|| shown.as_bool().map(|b| f64::from(u8::from(b)))).unwrap();
                let family = families.iter().find(|f| f.name == *family).unwrap_or_else(|| panic!("no {family}"));
                let value = match &family.samples[0].1 {
                    Sample::Counter(v) => *v as f64,
                    Sample::Gauge(v) => *v,
                    Sample::Histogram(_) | Sample::Buckets { .. } => panic!("{}", family.name),
                };
                let value =
                    if family.name.ends_with("_seconds") && pointer.ends_with("_ms") { value * 1e3 } else { value };
                assert_eq!(value, shown, "{} against {pointer}", family.name);
            }
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

//! A component's section of the run report and the live status: a typed
//! value ([`StatusSection`]) that names its section, shows itself as JSON,
//! and names the metric families it feeds ([`Family`]), so no reader looks
//! a value up by key and a renamed field breaks the build, not a plot.
//! `metrics` encodes the families; `report` lists the sections.

use std::any::Any;
use std::fmt::Debug;

use super::Histogram;

/// One component's status section.
pub trait StatusSection: Any + Debug + Send + Sync {
    /// The section's name in the report (`arbiter`, `serial`, `teleop`, ...;
    /// docs/report.md).
    fn section(&self) -> &'static str;
    /// The section as the report's JSON shows it.
    fn to_json(&self) -> serde_json::Value;
    /// The metric families this section feeds, with `component` (the name
    /// of the component it belongs to) in their labels.
    fn metric_families(&self, component: &str) -> Vec<Family> {
        let _ = component;
        Vec::new()
    }
}

/// A section that serializes itself under a fixed name: implementing this
/// (with `metric_families` when it feeds metrics) makes it a
/// [`StatusSection`].
pub trait NamedSection: serde::Serialize + Debug + Send + Sync + 'static {
    /// The section's name in the report.
    const SECTION: &'static str;
    /// As [`StatusSection::metric_families`].
    fn families(&self, component: &str) -> Vec<Family> {
        let _ = component;
        Vec::new()
    }
}

impl<T: NamedSection> StatusSection for T {
    fn section(&self) -> &'static str {
        T::SECTION
    }

    fn to_json(&self) -> serde_json::Value {
        json_of(self)
    }

    fn metric_families(&self, component: &str) -> Vec<Family> {
        self.families(component)
    }
}

impl dyn StatusSection {
    /// The section as its own type, if it is a `T`.
    pub fn downcast_ref<T: StatusSection>(&self) -> Option<&T> {
        (self as &dyn Any).downcast_ref::<T>()
    }
}

/// What kind of metric a family is.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum MetricKind {
    Counter,
    Gauge,
    Histogram,
}

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
/// adds), help, kind and labelled samples.
#[derive(Clone, Debug)]
pub struct Family {
    pub name: &'static str,
    pub help: &'static str,
    pub kind: MetricKind,
    pub samples: Vec<(Vec<(&'static str, String)>, Sample)>,
}

impl Family {
    pub fn new(name: &'static str, help: &'static str, kind: MetricKind) -> Family {
        Family { name, help, kind, samples: Vec::new() }
    }

    /// This family with one more sample.
    pub fn with(mut self, labels: Vec<(&'static str, String)>, sample: Sample) -> Family {
        self.samples.push((labels, sample));
        self
    }

    /// This family with one counter sample.
    pub fn counter(self, labels: Vec<(&'static str, String)>, value: u64) -> Family {
        self.with(labels, Sample::Counter(value))
    }

    /// This family with one gauge sample.
    pub fn gauge(self, labels: Vec<(&'static str, String)>, value: f64) -> Family {
        self.with(labels, Sample::Gauge(value))
    }

    /// One family per row (name, help, sample), each with one sample
    /// labelled `label`.
    pub fn each(label: (&'static str, &str), rows: &[(&'static str, &'static str, Sample)]) -> Vec<Family> {
        rows.iter()
            .map(|(name, help, sample)| {
                let kind = match sample {
                    Sample::Counter(_) => MetricKind::Counter,
                    Sample::Gauge(_) => MetricKind::Gauge,
                    Sample::Histogram(_) | Sample::Buckets { .. } => MetricKind::Histogram,
                };
                Family::new(name, help, kind).with(vec![(label.0, label.1.to_string())], sample.clone())
            })
            .collect()
    }
}

/// The JSON of a section that serializes itself (what `to_json` returns for
/// a `serde::Serialize` type; `Null` cannot happen for these types but is
/// what a failure would show).
pub fn json_of<T: serde::Serialize>(value: &T) -> serde_json::Value {
    serde_json::to_value(value).unwrap_or_default()
}

//! Both versions of the contract side by side: components and translators
//! built against `subsume:robot@0.1.0` (`test-relay-v1`,
//! `test-translator-v1`) run beside 0.2.0 ones (`test-relay`,
//! `translator-ascii`) in one graph, values cross between them, each
//! version's errors are counted, and a 0.2.0 scan reaches vector inputs of
//! either version as its ranges. Controlled time throughout.

use std::sync::{Arc, Mutex};
use std::time::Duration;

use subsume::contract::control::ControlCommand;
use subsume::contract::{Param, Scan, Value, ValueKind};
use subsume::robot::protocol::Profile;
use subsume::robot::translator::{DriveGeometry, ProfileTranslator, Translator};
use subsume::runtime::{CallError, Component, Convert, Graph, Outbox, Policy};
use subsume::sandbox::{Contract, GuestLimits, Sandbox, WasmArtifact};

use crate::support::{self, sandbox};

const MS: u64 = 1_000_000;
const LIMITS: GuestLimits = GuestLimits {
    memory_bytes: 16 << 20,
    budget: Duration::from_millis(20),
    max_emits: 256,
    max_message_bytes: 1 << 20,
    max_logs_per_s: 100,
    wall_capped: true,
};

fn artifact(sandbox: &Sandbox, name: &str) -> Arc<WasmArtifact> {
    sandbox.load(&std::fs::read(support::guest(name)).unwrap()).unwrap()
}

fn instance(sandbox: &Sandbox, name: &str) -> Box<dyn Component> {
    Box::new(sandbox.instantiate(&artifact(sandbox, name), name, &LIMITS, &[]).unwrap())
}

/// A native component that records what it receives.
#[derive(Clone, Default)]
struct Recorder(Arc<Mutex<Vec<Value>>>);

impl Component for Recorder {
    fn on_input(
        &mut self,
        _port: u32,
        value: &Value,
        _from: usize,
        _now: u64,
        _out: &mut Outbox,
    ) -> Result<(), CallError> {
        self.0.lock().unwrap().push(value.clone());
        Ok(())
    }
}

#[test]
fn each_component_is_bound_to_the_contract_it_was_built_against() {
    let sandbox = sandbox();
    assert_eq!(artifact(&sandbox, "test-relay").contract, Contract::V0_2);
    let old = artifact(&sandbox, "test-relay-v1");
    assert_eq!(old.contract, Contract::V0_1);
    // A 0.1.0 description reads like any other.
    assert_eq!(old.description.name, "test-relay-v1");
    assert_eq!(old.description.inputs.len(), 2);
}

#[test]
fn values_cross_between_versions_and_each_version_reports_its_errors() {
    let sandbox = sandbox();
    let mut graph = Graph::new();
    let source = graph.add("source", Box::new(subsume::runtime::Vacant), 1, 0.0, 0);
    let new = graph.add("new", instance(&sandbox, "test-relay"), 2, 0.0, 0);
    let old = graph.add("old", instance(&sandbox, "test-relay-v1"), 2, 0.0, 0);
    let recorder = Recorder::default();
    let sink = graph.add("sink", Box::new(recorder.clone()), 0, 0.0, 0);
    graph.connect(source, 0, new, 0, Policy::Queue { depth: 8 });
    graph.connect(new, 0, old, 0, Policy::Queue { depth: 8 });
    graph.connect(old, 0, sink, 0, Policy::Queue { depth: 8 });
    for (i, x) in [1.5, -2.0, 3.0].into_iter().enumerate() {
        graph.inject(source, 0, Value::Scalar(x), i as u64 * MS);
    }
    // The negative value passes the 0.2.0 relay and is refused (an `err`
    // result) by the 0.1.0 one, which keeps running.
    assert_eq!(*recorder.0.lock().unwrap(), vec![Value::Scalar(1.5), Value::Scalar(3.0)]);
    let old_stats = graph.stats(old).unwrap();
    assert_eq!((old_stats.errors, old_stats.last_error.as_deref()), (1, Some("negative input -2")));
    assert_eq!(graph.stats(new).unwrap().errors, 0);
}

#[test]
fn a_scan_reaches_vector_inputs_of_both_versions_as_its_ranges() {
    let sandbox = sandbox();
    let scan = Value::Scan(Scan {
        angle_min: -1.5,
        angle_increment: 0.75,
        range_min: 0.05,
        range_max: 4.0,
        ranges: vec![1.0, 2.0, 4.0, 0.5, 0.25],
    });
    let ranges = Value::Vector(vec![1.0, 2.0, 4.0, 0.5, 0.25]);
    for relay in ["test-relay", "test-relay-v1"] {
        let mut graph = Graph::new();
        let source = graph.add("source", Box::new(subsume::runtime::Vacant), 1, 0.0, 0);
        let node = graph.add(relay, instance(&sandbox, relay), 2, 0.0, 0);
        let recorder = Recorder::default();
        let sink = graph.add("sink", Box::new(recorder.clone()), 0, 0.0, 0);
        // vector-in is input 1; vector-out is output 1.
        graph.connect(source, 0, node, 1, Policy::Latest);
        graph.connect(node, 1, sink, 0, Policy::Latest);
        graph.inject(source, 0, scan.clone(), 0);
        assert_eq!(*recorder.0.lock().unwrap(), vec![ranges.clone()], "{relay}");
    }
}

#[test]
fn a_graph_connection_from_a_scan_into_a_native_vector_input_hands_over_the_ranges() {
    let scan = Value::Scan(Scan {
        angle_min: -0.5,
        angle_increment: 0.5,
        range_min: 0.0,
        range_max: 4.0,
        ranges: vec![1.0, 4.0, 0.5],
    });
    let mut graph = Graph::new();
    let source = graph.add("source", Box::new(subsume::runtime::Vacant), 1, 0.0, 0);
    let (ranges, whole) = (Recorder::default(), Recorder::default());
    let vector_sink = graph.add("vector-sink", Box::new(ranges.clone()), 0, 0.0, 0);
    let any_sink = graph.add("any-sink", Box::new(whole.clone()), 0, 0.0, 0);
    let convert = Convert::between(ValueKind::Scan, ValueKind::Vector);
    assert_eq!(convert, Convert::ScanToRanges);
    assert_eq!(Convert::between(ValueKind::Scan, ValueKind::Any), Convert::Nothing);
    graph.connect_converting(source, 0, vector_sink, 0, Policy::Latest, convert);
    graph.connect(source, 0, any_sink, 0, Policy::Latest);
    graph.inject(source, 0, scan.clone(), 0);
    assert_eq!(*ranges.0.lock().unwrap(), vec![Value::Vector(vec![1.0, 4.0, 0.5])]);
    assert_eq!(*whole.0.lock().unwrap(), vec![scan]);
}

#[test]
fn a_scan_input_of_a_0_2_0_component_keeps_the_geometry() {
    let sandbox = sandbox();
    let scan = Value::Scan(Scan {
        angle_min: -1.0,
        angle_increment: 0.5,
        range_min: 0.1,
        range_max: 3.0,
        ranges: vec![1.0, 2.0, 3.0, 0.5, 0.25],
    });
    let mut graph = Graph::new();
    let source = graph.add("source", Box::new(subsume::runtime::Vacant), 1, 0.0, 0);
    let node = graph.add("relay", instance(&sandbox, "test-relay"), 3, 0.0, 0);
    let recorder = Recorder::default();
    let sink = graph.add("sink", Box::new(recorder.clone()), 0, 0.0, 0);
    // scan-in is input 2; scan-out is output 2.
    graph.connect(source, 0, node, 2, Policy::Latest);
    graph.connect(node, 2, sink, 0, Policy::Latest);
    graph.inject(source, 0, scan.clone(), 0);
    assert_eq!(*recorder.0.lock().unwrap(), vec![scan]);
}

#[test]
fn translators_of_both_versions_write_the_builtin_profiles_bytes() {
    let sandbox = sandbox();
    let params = [
        Param { name: "wheel-base".into(), value: "0.3".into() },
        Param { name: "max-wheel-speed".into(), value: "0.5".into() },
    ];
    let mut builtin = ProfileTranslator::new(Profile::Ascii, DriveGeometry { wheel_base: 0.3, max_wheel_speed: 0.5 });
    for (name, contract) in [("translator-ascii", Contract::V0_2), ("test-translator-v1", Contract::V0_1)] {
        let artifact = sandbox.load_translator(&std::fs::read(support::guest(name)).unwrap()).unwrap();
        assert_eq!(artifact.contract, contract, "{name}");
        let mut wasm = sandbox.instantiate_translator(&artifact, "motors", &LIMITS, &params).unwrap();
        // Neither asks for opening or closing bytes or a poll.
        assert_eq!((wasm.plan().opening.len(), wasm.plan().poll_period_ms, wasm.plan().closing.len()), (0, 0, 0));
        for command in ["STOP", "VEL 0.2 0", "VEL 0 1", "VEL -0.1 0.5"] {
            let command: ControlCommand = command.parse().unwrap();
            let (mut ours, mut theirs) = (Vec::new(), Vec::new());
            Translator::encode(&mut wasm, &command, &mut ours).unwrap();
            builtin.encode(&command, &mut theirs).unwrap();
            assert_eq!(ours, theirs, "{name}: {command}");
        }
        let mut feedback = Vec::new();
        Translator::decode(&mut wasm, b"O 1000 -500 250\nB 1\n", &mut feedback).unwrap();
        assert_eq!(feedback.len(), 2, "{name}");
    }
}

//! The runtime with real guests from guest-components/rust, driven with
//! controlled time: `Graph::step(now)` is called with chosen instants, so
//! rates and routing are checked exactly, without sleeping.

use std::sync::{Arc, Mutex};
use std::time::Duration;

use subsume::config::Policy;
use subsume::contract::{Param, Value};
use subsume::runtime::{CallError, Component, ComponentState, Graph, Outbox};
use subsume::sandbox::{GuestLimits, Sandbox};

use crate::support::{self, sandbox};

const MS: u64 = 1_000_000;

/// Instantiates guest `name` with `params` over its declared defaults.
fn guest(
    sandbox: &Sandbox,
    name: &str,
    params: &[(&str, &str)],
    budget: Duration,
) -> Result<Box<dyn Component>, String> {
    let bytes = std::fs::read(support::guest(name)).unwrap();
    let artifact = sandbox.load(&bytes).map_err(|e| e.to_string())?;
    let params: Vec<Param> = artifact
        .description
        .params
        .iter()
        .map(|spec| {
            let value =
                params.iter().find(|(n, _)| *n == spec.name).map_or(spec.default_value.clone(), |(_, v)| v.to_string());
            Param { name: spec.name.clone(), value }
        })
        .collect();
    let component = sandbox
        .instantiate(
            &artifact,
            name,
            &GuestLimits { memory_bytes: 16 << 20, budget, ..GuestLimits::default() },
            &params,
        )
        .map_err(|e| e.to_string())?;
    Ok(Box::new(component))
}

/// A native component that records what it receives.
#[derive(Clone, Default)]
struct Recorder(Arc<Mutex<Vec<(u32, Value, u64)>>>);

impl Recorder {
    fn scalars(&self) -> Vec<f64> {
        self.0
            .lock()
            .unwrap()
            .iter()
            .map(|(_, v, _)| match v {
                Value::Scalar(x) => *x,
                other => panic!("expected a scalar, got {other:?}"),
            })
            .collect()
    }
}

impl Component for Recorder {
    fn on_input(
        &mut self,
        port: u32,
        value: &Value,
        _from: usize,
        now_ns: u64,
        _out: &mut Outbox,
    ) -> Result<(), CallError> {
        self.0.lock().unwrap().push((port, value.clone(), now_ns));
        Ok(())
    }
    fn tick(&mut self, _now_ns: u64, _out: &mut Outbox) -> Result<(), CallError> {
        Ok(())
    }
}

const BUDGET: Duration = Duration::from_millis(20);

#[test]
fn values_flow_from_guest_to_guest_within_the_cycle() {
    let sandbox = sandbox();
    let mut graph = Graph::new();
    let counter = graph.add("counter", guest(&sandbox, "test-counter", &[], BUDGET).unwrap(), 1, 10.0, 0);
    let relay = graph.add("relay", guest(&sandbox, "test-relay", &[], BUDGET).unwrap(), 2, 0.0, 0);
    let recorder = Recorder::default();
    let sink = graph.add("sink", Box::new(recorder.clone()), 0, 0.0, 0);
    graph.connect(counter, 0, relay, 0, Policy::Latest);
    graph.connect(relay, 0, sink, 0, Policy::Latest);

    for step in 0..3 {
        graph.step(step * 100 * MS);
        // Counter -> relay -> sink within the same cycle.
        assert_eq!(recorder.scalars().len() as u64, step + 1);
    }
    assert_eq!(recorder.scalars(), vec![0.0, 1.0, 2.0]);
    let times: Vec<u64> = recorder.0.lock().unwrap().iter().map(|(_, _, t)| *t).collect();
    assert_eq!(times, vec![0, 100 * MS, 200 * MS]);
    let relay_stats = graph.stats(relay).unwrap();
    assert_eq!((relay_stats.messages_in, relay_stats.messages_out, relay_stats.ticks), (3, 3, 0));
    assert_eq!(graph.messages_routed(), 6);
}

#[test]
fn each_connection_has_its_own_mailbox() {
    let sandbox = sandbox();
    let mut graph = Graph::new();
    let recorder = Recorder::default();
    let sink = graph.add("sink", Box::new(recorder.clone()), 0, 0.0, 0);
    // Five guests feed one input over five latest-value connections.
    for i in 0..5 {
        let start = (i * 10).to_string();
        let counter =
            graph.add("counter", guest(&sandbox, "test-counter", &[("start", &start)], BUDGET).unwrap(), 1, 10.0, 0);
        graph.connect(counter, 0, sink, 0, Policy::Latest);
    }
    graph.step(0);
    assert_eq!(recorder.scalars(), vec![0.0, 10.0, 20.0, 30.0, 40.0]);
    assert_eq!(graph.messages_dropped(), 0);
}

#[test]
fn latest_keeps_the_newest_value_and_queue_keeps_order_dropping_the_oldest() {
    let sandbox = sandbox();
    let mut graph = Graph::new();
    // Four counters tick in one cycle into a relay's queue; the relay then
    // handles the four values in a row, emitting four values on one output
    // before either sink is called.
    let relay = graph.add("relay", guest(&sandbox, "test-relay", &[], BUDGET).unwrap(), 2, 0.0, 0);
    for i in 0..4 {
        let start = i.to_string();
        let counter =
            graph.add("counter", guest(&sandbox, "test-counter", &[("start", &start)], BUDGET).unwrap(), 1, 10.0, 0);
        graph.connect(counter, 0, relay, 0, Policy::Queue { depth: 8 });
    }
    let latest = Recorder::default();
    let queued = Recorder::default();
    let latest_sink = graph.add("latest", Box::new(latest.clone()), 0, 0.0, 0);
    let queue_sink = graph.add("queued", Box::new(queued.clone()), 0, 0.0, 0);
    graph.connect(relay, 0, latest_sink, 0, Policy::Latest);
    graph.connect(relay, 0, queue_sink, 0, Policy::Queue { depth: 2 });
    graph.step(0);

    assert_eq!(graph.stats(relay).unwrap().messages_in, 4);
    assert_eq!(latest.scalars(), vec![3.0]);
    assert_eq!(queued.scalars(), vec![2.0, 3.0]);
    let latest_connection = graph.connection_stats(4).unwrap();
    assert_eq!((latest_connection.routed, latest_connection.overwritten, latest_connection.delivered), (4, 3, 1));
    let queue_connection = graph.connection_stats(5).unwrap();
    assert_eq!((queue_connection.routed, queue_connection.dropped, queue_connection.delivered), (4, 2, 2));
    assert_eq!(graph.messages_dropped(), 2);
    assert_eq!(graph.stats(queue_sink).unwrap().messages_dropped, 2);
}

#[test]
fn components_tick_at_their_own_rates() {
    let sandbox = sandbox();
    let mut graph = Graph::new();
    let rates = [10.0, 50.0, 200.0, 0.0];
    let ids: Vec<usize> = rates
        .iter()
        .map(|&rate| graph.add("counter", guest(&sandbox, "test-counter", &[], BUDGET).unwrap(), 1, rate, 0))
        .collect();
    // One simulated second, stepped every millisecond.
    for ms in 0..1000 {
        graph.step(ms * MS);
    }
    let ticks: Vec<u64> = ids.iter().map(|&i| graph.stats(i).unwrap().ticks).collect();
    assert_eq!(ticks, vec![10, 50, 200, 0]);
    assert!(ids.iter().all(|&i| graph.stats(i).unwrap().missed_ticks == 0));
    assert_eq!(graph.next_due_ns(), Some(1000 * MS));
}

#[test]
fn a_loop_that_falls_behind_skips_and_counts_missed_ticks() {
    let sandbox = sandbox();
    let mut graph = Graph::new();
    let counter = graph.add("counter", guest(&sandbox, "test-counter", &[], BUDGET).unwrap(), 1, 100.0, 0);
    graph.step(0);
    graph.step(55 * MS);
    let stats = graph.stats(counter).unwrap();
    assert_eq!((stats.ticks, stats.missed_ticks), (2, 4));
    // Back on the 10 ms grid, not 55 + 10.
    assert_eq!(graph.next_due_ns(), Some(60 * MS));
}

/// Runs `faulty` (mode, after) beside a healthy counter for 10 cycles of
/// 10 ms; returns the faulty component's state, the counter's ticks, what the
/// faulty one emitted and its reported errors.
fn run_beside_a_healthy_counter(mode: &str, after: &str, budget: Duration) -> (ComponentState, u64, Vec<f64>, u64) {
    let sandbox = sandbox();
    let mut graph = Graph::new();
    let faulty = graph.add(
        "faulty",
        guest(&sandbox, "test-faulty", &[("mode", mode), ("after", after)], budget).unwrap(),
        1,
        100.0,
        0,
    );
    let counter = graph.add("counter", guest(&sandbox, "test-counter", &[], BUDGET).unwrap(), 1, 100.0, 0);
    let from_faulty = Recorder::default();
    let from_counter = Recorder::default();
    let a = graph.add("a", Box::new(from_faulty.clone()), 0, 0.0, 0);
    let b = graph.add("b", Box::new(from_counter.clone()), 0, 0.0, 0);
    graph.connect(faulty, 0, a, 0, Policy::Queue { depth: 100 });
    graph.connect(counter, 0, b, 0, Policy::Queue { depth: 100 });
    for i in 0..10 {
        graph.step(i * 10 * MS);
    }
    assert_eq!(from_counter.scalars().len(), 10, "the healthy counter's values all arrive");
    let errors = graph.stats(faulty).unwrap().errors;
    (graph.state(faulty).unwrap().clone(), graph.stats(counter).unwrap().ticks, from_faulty.scalars(), errors)
}

fn fault_reason(state: &ComponentState) -> &str {
    match state {
        ComponentState::Faulted { reason, .. } => reason,
        ComponentState::Running => panic!("expected the component to be faulted"),
    }
}

#[test]
fn a_trapping_guest_faults_alone() {
    let (state, counter_ticks, emitted, _) = run_beside_a_healthy_counter("trap-on-tick", "3", BUDGET);
    assert!(fault_reason(&state).starts_with("tick: trapped"), "{state:?}");
    assert_eq!(emitted, vec![1.0, 2.0, 3.0], "good ticks before the trap are delivered, none after");
    assert_eq!(counter_ticks, 10);
}

#[test]
fn a_guest_that_overruns_its_budget_is_stopped() {
    let (state, counter_ticks, emitted, _) =
        run_beside_a_healthy_counter("loop-on-tick", "2", Duration::from_millis(5));
    let reason = fault_reason(&state);
    assert!(reason.starts_with("tick: exceeded its cpu-time budget of 5 ms (used "), "{reason}");
    assert_eq!(emitted, vec![1.0, 2.0]);
    assert_eq!(counter_ticks, 10);
}

#[test]
fn emitting_on_a_port_that_does_not_exist_faults() {
    let (state, counter_ticks, _, _) = run_beside_a_healthy_counter("bad-port-on-tick", "0", BUDGET);
    assert_eq!(fault_reason(&state), "tick: emitted on output port 99, but the component declares 4 output(s)");
    assert_eq!(counter_ticks, 10);
}

#[test]
fn an_err_result_is_counted_and_the_guest_keeps_running() {
    let (state, counter_ticks, emitted, errors) = run_beside_a_healthy_counter("error-on-tick", "4", BUDGET);
    assert_eq!(state, ComponentState::Running);
    assert_eq!(emitted, vec![1.0, 2.0, 3.0, 4.0]);
    assert_eq!(errors, 6);
    assert_eq!(counter_ticks, 10);
}

#[test]
fn init_can_refuse_to_start_with_a_message() {
    let sandbox = sandbox();
    let err = guest(&sandbox, "test-faulty", &[("mode", "error-on-init")], BUDGET).err().unwrap_or_default();
    assert_eq!(err, "init() failed: refusing to start, as asked");
}

#[test]
fn a_faulted_component_receives_nothing_more() {
    let sandbox = sandbox();
    let mut graph = Graph::new();
    let counter = graph.add("counter", guest(&sandbox, "test-counter", &[], BUDGET).unwrap(), 1, 100.0, 0);
    let relay = graph.add("relay", guest(&sandbox, "test-relay", &[], BUDGET).unwrap(), 2, 0.0, 0);
    graph.connect(counter, 0, relay, 0, Policy::Queue { depth: 4 });
    graph.step(0);
    graph.fault(relay, "stopped by the test".into(), 0);
    graph.step(10 * MS);
    graph.step(20 * MS);
    assert_eq!(graph.stats(relay).unwrap().messages_in, 1);
    assert_eq!(graph.stats(counter).unwrap().ticks, 3);
}

/// A native component whose tick faults.
struct FaultsOnTick;

impl Component for FaultsOnTick {
    fn tick(&mut self, _now_ns: u64, _out: &mut Outbox) -> Result<(), CallError> {
        Err(CallError::Fault("tick: faulted by the test".into()))
    }
}

/// A native component that takes `0` to hear of a peer's fault.
struct SlowToHear(Duration);

impl Component for SlowToHear {
    fn peer_faulted(&mut self, _component: usize, _now_ns: u64, _out: &mut Outbox) {
        std::thread::sleep(self.0);
    }
}

#[test]
fn a_faulting_component_is_not_charged_the_time_its_peers_take_to_hear_of_it() {
    // A CI run charged a faulting guest 132 ms for a call capped at 50 ms:
    // its call time included every peer's `peer_faulted`.
    let hearing = Duration::from_millis(300);
    let mut graph = Graph::new();
    let faulty = graph.add("faulty", Box::new(FaultsOnTick), 0, 10.0, 0);
    let peers: Vec<usize> =
        (0..2).map(|n| graph.add(&format!("peer{n}"), Box::new(SlowToHear(hearing)), 0, 0.0, 0)).collect();
    graph.step(0);
    assert!(matches!(graph.state(faulty), Some(ComponentState::Faulted { .. })), "{:?}", graph.state(faulty));
    let stats = graph.stats(faulty).unwrap();
    assert_eq!(stats.calls, 1);
    // The peers took 600 ms between them; the call itself returns at once.
    assert!(
        Duration::from_nanos(stats.call_ns) < hearing,
        "charged {:?} for a call that returned at once",
        Duration::from_nanos(stats.call_ns)
    );
    for peer in peers {
        assert_eq!(graph.stats(peer).unwrap().calls, 0);
    }
}

#[test]
fn the_description_comes_from_the_guest() {
    let sandbox = sandbox();
    let bytes = std::fs::read(support::guest("avoider")).unwrap();
    let artifact = sandbox.load(&bytes).unwrap();
    let d = &artifact.description;
    assert_eq!(d.name, "avoider");
    assert_eq!(d.default_priority, Some(3));
    assert_eq!(d.inputs.iter().map(|p| p.name.as_str()).collect::<Vec<_>>(), vec!["ranges"]);
    assert_eq!(d.outputs.iter().map(|p| p.name.as_str()).collect::<Vec<_>>(), vec!["cmd"]);
    assert_eq!(artifact.sha256.len(), 64);
}

#[test]
fn compiled_components_are_cached_and_a_bad_cache_entry_is_recompiled() {
    support::guest_dir();
    let cache = tempfile::tempdir().unwrap();
    let bytes = std::fs::read(support::guest("test-relay")).unwrap();
    {
        let sandbox = Sandbox::new(Some(cache.path().to_path_buf())).unwrap();
        sandbox.load(&bytes).unwrap();
    }
    // One compiled component, beside the folder of the function cache.
    let entries: Vec<_> = std::fs::read_dir(cache.path())
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.file_name().is_none_or(|n| n != "functions"))
        .collect();
    assert_eq!(entries.len(), 1, "{entries:?}");
    assert!(entries[0].extension().is_some_and(|x| x == "cwasm"));
    assert!(cache.path().join("functions").is_dir(), "no function cache beside it");
    // A second engine loads from the cache.
    let sandbox = Sandbox::new(Some(cache.path().to_path_buf())).unwrap();
    assert_eq!(sandbox.load(&bytes).unwrap().description.name, "test-relay");
    // A damaged entry is not trusted: the component is compiled again.
    std::fs::write(&entries[0], b"garbage").unwrap();
    let sandbox = Sandbox::new(Some(cache.path().to_path_buf())).unwrap();
    assert_eq!(sandbox.load(&bytes).unwrap().description.name, "test-relay");
    assert!(std::fs::read(&entries[0]).unwrap().len() > 1000, "the entry was rewritten");
}

#[test]
fn a_faulted_component_restarts_with_backoff_until_its_restarts_run_out() {
    use subsume::runtime::RestartPolicy;
    let sandbox = sandbox();
    let bytes = std::fs::read(support::guest("test-faulty")).unwrap();
    let artifact = sandbox.load(&bytes).unwrap();
    let params = vec![
        Param { name: "mode".into(), value: "trap-on-tick".into() },
        Param { name: "after".into(), value: "2".into() },
    ];
    let limits = GuestLimits { memory_bytes: 16 << 20, budget: BUDGET, ..GuestLimits::default() };
    let first = sandbox.instantiate(&artifact, "faulty", &limits, &params).unwrap();
    let mut graph = Graph::new();
    let faulty = graph.add("faulty", Box::new(first), 4, 100.0, 0);
    let recorder = Recorder::default();
    let sink = graph.add("sink", Box::new(recorder.clone()), 0, 0.0, 0);
    graph.connect(faulty, 0, sink, 0, Policy::Queue { depth: 100 });
    let policy = RestartPolicy { max_restarts: 2, backoff_ns: 1_000 * MS };
    graph.set_restart(faulty, policy, sandbox.restarter(artifact, "faulty", limits, params));

    let faulted = |graph: &Graph| matches!(graph.state(faulty), Some(ComponentState::Faulted { .. }));
    // Life 1: good ticks at 0 and 10 ms, the trap at 20 ms.
    for ms in [0, 10, 20] {
        graph.step(ms * MS);
    }
    assert!(faulted(&graph));
    // The first restart waits 1 s.
    graph.step(1_019 * MS);
    assert!(faulted(&graph));
    assert_eq!(graph.next_due_ns(), Some(1_020 * MS));
    // Life 2 starts at 1020 ms and traps at 1040 ms; the next wait is 2 s.
    for ms in [1_020, 1_030, 1_040] {
        graph.step(ms * MS);
    }
    assert!(faulted(&graph));
    assert_eq!(graph.stats(faulty).unwrap().restarts, 1);
    // Life 3 (the last restart allowed).
    for ms in [3_040, 3_050, 3_060] {
        graph.step(ms * MS);
    }
    assert!(faulted(&graph));
    graph.step(60_000 * MS);
    assert!(faulted(&graph), "no restarts left");
    assert_eq!(graph.stats(faulty).unwrap().restarts, 2);
    // Each life emitted its two good ticks, counting from 1 again.
    assert_eq!(recorder.scalars(), vec![1.0, 2.0, 1.0, 2.0, 1.0, 2.0]);
}

/// Records every input a graph delivers to one component.
struct InputsOf {
    component: usize,
    seen: Arc<Mutex<Vec<(u32, Value, u64)>>>,
}

impl subsume::runtime::Tap for InputsOf {
    fn call(&mut self, index: usize, call: subsume::runtime::Call<'_>, now_ns: u64) {
        if let (true, subsume::runtime::Call::Input { port, value, .. }) = (index == self.component, call) {
            self.seen.lock().unwrap().push((port, value.clone(), now_ns));
        }
    }
    fn emitted(&mut self, _: usize, _: u32, _: &Value, _: u64) {}
    fn faulted(&mut self, _: usize, _: &str, _: u64) {}
    fn restarted(&mut self, _: usize, _: u64, _: u64) {}
}

/// A WASM component wired to the envelope's `interventions` output, in a
/// graph built from a robot file: a driver heads out of the geofence, the
/// envelope holds it, and the component receives one message saying so
/// (stopped, geofence, the reading), not one per command.
#[test]
fn a_component_wired_to_the_envelope_hears_of_the_geofence_hold() {
    let sandbox = sandbox();
    let dir = tempfile::tempdir().unwrap();
    let robot = dir.path().join("fenced.xml");
    let relay = support::guest("test-relay");
    std::fs::write(
        &robot,
        format!(
            r#"<robot name="fenced">
  <platform name="control">
    <component name="driver" source="builtin:publish" rate="20" priority="1">
      <param name="kind" value="command"/><param name="value" value="VEL 0.3 0"/>
    </component>
    <component name="odometry" source="builtin:publish" rate="20">
      <param name="kind" value="vector"/><param name="value" value="3.9 1.5 0"/>
    </component>
    <component name="arbiter" source="builtin:arbiter" rate="20"/>
    <component name="envelope" source="builtin:envelope" rate="20">
      <param name="geofence" value="0,0 4,0 4,3 0,3"/>
    </component>
    <component name="listener" source="{}" rate="0"/>
    <component name="motors" source="builtin:log" rate="0"/>
    <component name="heard" source="builtin:log" rate="0"/>
    <connect from="driver.out" to="arbiter.commands"/>
    <connect from="odometry.out" to="envelope.pose"/>
    <connect from="arbiter.cmd" to="envelope.cmd"/>
    <connect from="envelope.cmd" to="motors.in"/>
    <connect from="envelope.interventions" to="listener.text-in"/>
    <connect from="listener.text-out" to="heard.in"/>
  </platform>
</robot>
"#,
            relay.display()
        ),
    )
    .unwrap();
    let mut loader = subsume::assemble::Loader::new(&sandbox);
    let config = subsume::config::load(&robot, &mut loader).unwrap_or_else(|d| panic!("{d}"));
    let listener = config.components.iter().position(|c| c.name == "listener").unwrap();
    let clock = subsume::runtime::control_loop::Clock::new();
    let shutdown = subsume::runtime::control_loop::Shutdown::new();
    let mut graph = subsume::assemble::build_graph(&config, &mut loader, clock.clone(), &shutdown.waker())
        .unwrap_or_else(|e| panic!("{e:?}"));
    let seen = Arc::new(Mutex::new(Vec::new()));
    graph.set_tap(Box::new(InputsOf { component: listener, seen: seen.clone() }));
    // Two seconds of graph time, 100 cycles a second.
    let start = clock.now_ns();
    for cycle in 0..=200 {
        graph.step(start + cycle * 10 * MS);
    }
    let heard: Vec<serde_json::Value> = seen
        .lock()
        .unwrap()
        .iter()
        .map(|(port, value, _)| match value {
            Value::Text(text) => {
                assert_eq!(*port, 3, "text-in");
                serde_json::from_str(text).unwrap()
            }
            other => panic!("the listener got {other:?}"),
        })
        .collect();
    assert_eq!(heard.len(), 1, "one message for the whole hold: {heard:?}");
    let hold = &heard[0];
    assert_eq!((hold["action"].as_str(), hold["cause"].as_str()), (Some("stopped"), Some("geofence")), "{hold}");
    assert_eq!((hold["command"].as_str(), hold["output"].as_str()), (Some("VEL 0.3 0.0"), Some("STOP")), "{hold}");
    assert!(hold["reading"]["edge_m"].as_f64().is_some_and(|e| (e - 0.1).abs() < 1e-9), "{hold}");
    assert_eq!(hold["reading"]["outside"], false, "{hold}");
    assert!(hold["text"].as_str().unwrap().starts_with("stopped VEL 0.3 0.0: geofence"), "{hold}");
    // The listener ran normally and forwarded what it heard.
    let state = graph.state(listener).unwrap();
    assert!(matches!(state, ComponentState::Running), "{state:?}");
}

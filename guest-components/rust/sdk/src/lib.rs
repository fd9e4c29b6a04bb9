//! `subsume-guest`: write a subsume robot component in Rust as a struct and a
//! few methods.
//!
//! ```ignore
//! use subsume_guest::{Component, Description, Params, Value, ValueKind, emit, input, output};
//!
//! struct Doubler;
//!
//! impl Component for Doubler {
//!     fn describe() -> Description {
//!         Description::new("doubler", "Doubles every scalar it receives")
//!             .input(input("in", ValueKind::Scalar, "any number"))
//!             .output(output("out", ValueKind::Scalar, "twice the input"))
//!     }
//!     fn init(_params: &Params) -> Result<Self, String> { Ok(Doubler) }
//!     fn on_input(&mut self, _port: u32, value: Value) -> Result<(), String> {
//!         if let Value::Scalar(x) = value { emit(0, &Value::Scalar(2.0 * x)); }
//!         Ok(())
//!     }
//! }
//! subsume_guest::component!(Doubler);
//! ```
//!
//! The SDK owns the wit-bindgen boilerplate: the bindings of the
//! `subsume:robot/component` world (`subsume:robot@0.2.0`), the one instance
//! of the component's state and the export glue. An `Err` from `on_input` or
//! `tick` reaches the host through `host.report`: it is logged and counted,
//! and the component keeps running.

#[doc(hidden)]
// Generated: a `value` holding a `scan` flattens to many core arguments.
#[allow(clippy::too_many_arguments)]
pub mod bindings {
    wit_bindgen::generate!({
        world: "component",
        path: "../../../wit",
        pub_export_macro: true,
        export_macro_name: "__export_component",
        default_bindings_module: "subsume_guest::bindings",
    });
}

#[doc(hidden)]
#[allow(clippy::too_many_arguments)]
pub mod translator_bindings {
    wit_bindgen::generate!({
        world: "translator",
        path: "../../../wit",
        pub_export_macro: true,
        export_macro_name: "__export_translator",
        default_bindings_module: "subsume_guest::translator_bindings",
    });
}

#[doc(hidden)]
#[allow(clippy::too_many_arguments)]
pub mod scorer_bindings {
    wit_bindgen::generate!({
        world: "scorer",
        path: "../../../wit",
        pub_export_macro: true,
        export_macro_name: "__export_scorer",
        default_bindings_module: "subsume_guest::scorer_bindings",
    });
}

pub mod drive;

pub use scorer_bindings::{Episode, Event, Goal as TaskGoal, Position, Sample, SubScore, Verdict};

pub use translator_bindings::subsume::robot::types::{Decoded, Feedback, LinkPlan, Pose, Scan as FeedbackScan};

pub use bindings::subsume::robot::types::{
    Description as RawDescription, LogLevel, Param, ParamKind, ParamSpec, PortSpec, Scan, Value, ValueKind,
};

/// What a component implements. `describe` is static (called before `init`);
/// `init` builds the component's state from its parameters.
pub trait Component: Sized + 'static {
    /// Ports, parameters and default priority. Must not depend on parameters.
    fn describe() -> Description;
    /// Builds the component from its parameters (every declared parameter is
    /// present: the host fills in defaults). `Err` refuses to start.
    fn init(params: &Params) -> Result<Self, String>;
    /// A new value arrived on input `port` (index into the declared inputs).
    fn on_input(&mut self, port: u32, value: Value) -> Result<(), String> {
        let _ = (port, value);
        Ok(())
    }
    /// Called at the component's configured rate.
    fn tick(&mut self, now_ns: u64) -> Result<(), String> {
        let _ = now_ns;
        Ok(())
    }
}

/// Builder for the component's self-description.
#[derive(Clone, Debug)]
pub struct Description(RawDescription);

impl Description {
    /// A description with no ports, no parameters and no default priority.
    pub fn new(name: &str, summary: &str) -> Self {
        Description(RawDescription {
            name: name.to_string(),
            version: "0.1.0".to_string(),
            summary: summary.to_string(),
            inputs: Vec::new(),
            outputs: Vec::new(),
            params: Vec::new(),
            default_priority: None,
        })
    }
    pub fn version(mut self, version: &str) -> Self {
        self.0.version = version.to_string();
        self
    }
    /// Adds an input port; its index is the number of inputs added before it.
    pub fn input(mut self, port: PortSpec) -> Self {
        self.0.inputs.push(port);
        self
    }
    /// Adds an output port; its index is the number of outputs added before it.
    pub fn output(mut self, port: PortSpec) -> Self {
        self.0.outputs.push(port);
        self
    }
    pub fn param(mut self, param: ParamSpec) -> Self {
        self.0.params.push(param);
        self
    }
    /// Subsumption priority of this component's motion commands (higher wins).
    pub fn priority(mut self, priority: i32) -> Self {
        self.0.default_priority = Some(priority);
        self
    }
    pub fn into_raw(self) -> RawDescription {
        self.0
    }
}

/// An input port spec.
pub fn input(name: &str, kind: ValueKind, doc: &str) -> PortSpec {
    PortSpec { name: name.to_string(), kind, doc: doc.to_string() }
}

/// An output port spec.
pub fn output(name: &str, kind: ValueKind, doc: &str) -> PortSpec {
    input(name, kind, doc)
}

/// A parameter spec; `default` is written as it would be in the XML file.
pub fn param(name: &str, kind: ParamKind, default: &str, doc: &str) -> ParamSpec {
    ParamSpec { name: name.to_string(), kind, default_value: default.to_string(), doc: doc.to_string() }
}

/// The parameters handed to `init`, already checked by the host against
/// their declared kinds.
#[derive(Clone, Debug, Default)]
pub struct Params(pub Vec<Param>);

impl Params {
    /// The text of parameter `name`, if present.
    pub fn text(&self, name: &str) -> Option<&str> {
        self.0.iter().find(|p| p.name == name).map(|p| p.value.as_str())
    }
    /// Parameter `name` as a number; `Err` names the parameter.
    pub fn number(&self, name: &str) -> Result<f64, String> {
        let text = self.text(name).ok_or_else(|| format!("missing parameter '{name}'"))?;
        text.trim().parse::<f64>().map_err(|_| format!("parameter '{name}': '{text}' is not a number"))
    }
    /// Parameter `name` as a whole number; `Err` names the parameter.
    pub fn integer(&self, name: &str) -> Result<i64, String> {
        let text = self.text(name).ok_or_else(|| format!("missing parameter '{name}'"))?;
        text.trim().parse::<i64>().map_err(|_| format!("parameter '{name}': '{text}' is not a whole number"))
    }
    /// Parameter `name` as a flag (`true`/`false`).
    pub fn flag(&self, name: &str) -> Result<bool, String> {
        match self.text(name).map(str::trim) {
            Some("true") => Ok(true),
            Some("false") => Ok(false),
            Some(other) => Err(format!("parameter '{name}': '{other}' is not true or false")),
            None => Err(format!("missing parameter '{name}'")),
        }
    }
}

/// Sends `value` on output `port` (index into the declared outputs).
pub fn emit(port: u32, value: &Value) {
    bindings::subsume::robot::host::emit(port, value);
}

/// Writes `message` to the host log at `level`.
pub fn log(level: LogLevel, message: &str) {
    bindings::subsume::robot::host::log(level, message);
}

/// The host's monotonic clock, in nanoseconds since the host started.
pub fn now_ns() -> u64 {
    bindings::subsume::robot::host::now_ns()
}

/// Tells the host the current call failed (the export glue does this with
/// the `Err` of `on_input` and `tick`).
pub fn report(message: &str) {
    bindings::subsume::robot::host::report(message);
}

/// Exports `$component` (a type implementing [`Component`]) as the
/// component's implementation of the `subsume:robot/component` world.
#[macro_export]
macro_rules! component {
    ($component:ty) => {
        #[doc(hidden)]
        struct __SubsumeExport;

        ::std::thread_local! {
            static __SUBSUME_STATE: ::core::cell::RefCell<::core::option::Option<$component>> =
                const { ::core::cell::RefCell::new(::core::option::Option::None) };
        }

        impl $crate::bindings::Guest for __SubsumeExport {
            fn describe() -> $crate::RawDescription {
                <$component as $crate::Component>::describe().into_raw()
            }
            fn init(params: ::std::vec::Vec<$crate::Param>) -> ::core::result::Result<(), ::std::string::String> {
                let state = <$component as $crate::Component>::init(&$crate::Params(params))?;
                __SUBSUME_STATE.with(|cell| *cell.borrow_mut() = ::core::option::Option::Some(state));
                ::core::result::Result::Ok(())
            }
            fn on_input(port: u32, value: $crate::Value) {
                let result = __SUBSUME_STATE.with(|cell| match cell.borrow_mut().as_mut() {
                    ::core::option::Option::Some(state) => $crate::Component::on_input(state, port, value),
                    ::core::option::Option::None => ::core::result::Result::Err("on-input called before init".into()),
                });
                if let ::core::result::Result::Err(message) = result {
                    $crate::report(&message);
                }
            }
            fn tick(now_ns: u64) {
                let result = __SUBSUME_STATE.with(|cell| match cell.borrow_mut().as_mut() {
                    ::core::option::Option::Some(state) => $crate::Component::tick(state, now_ns),
                    ::core::option::Option::None => ::core::result::Result::Err("tick called before init".into()),
                });
                if let ::core::result::Result::Err(message) = result {
                    $crate::report(&message);
                }
            }
        }

        $crate::bindings::__export_component!(__SubsumeExport with_types_in $crate::bindings);
    };
}

/// What a hardware translator implements (the `translator` world): the only
/// code that knows a motor controller's bytes.
pub trait Translator: Sized + 'static {
    /// Builds the translator from the serial link's parameters.
    fn init(params: &Params) -> Result<Self, String>;
    /// The bytes for one control string; `Err` when the hardware cannot
    /// carry it.
    fn encode(&mut self, command: &str) -> Result<Vec<u8>, String>;
    /// Feeds bytes from the controller; returns the feedback they complete.
    fn decode(&mut self, bytes: &[u8]) -> Decoded;
    /// What the link sends on opening and closing the device, and how often
    /// it calls `poll` (asked once, after `init`). The default: nothing.
    fn link(&self) -> LinkPlan {
        LinkPlan { opening: Vec::new(), poll_period_ms: 0, closing: Vec::new() }
    }
    /// Bytes to send at a poll (a sensor request, a keep-alive).
    fn poll(&mut self, now_ns: u64) -> Vec<u8> {
        let _ = now_ns;
        Vec::new()
    }
    /// The controller's fault status the last `decode` completed, taken:
    /// `Some(text)` naming what is wrong (e.g. "m1 over current warning"),
    /// `Some("")` when the controller reports no fault, `None` when those
    /// bytes completed no status (the host keeps the last). The export glue
    /// hands it to the host through `host.report` during `decode` (how a
    /// translator tells the host its controller's fault). The default: none.
    fn fault(&mut self) -> Option<String> {
        None
    }
}

/// Tells the host the controller's fault status from inside a translator's
/// `decode` (the [`translator!`] glue calls it with [`Translator::fault`]).
#[doc(hidden)]
pub fn report_fault(text: &str) {
    translator_bindings::subsume::robot::host::report(text);
}

/// Exports `$translator` (a type implementing [`Translator`]) as the
/// component's implementation of the `subsume:robot/translator` world. In a
/// fuzz build (`--cfg fuzzing`, see docs/fuzzing.md) it exports nothing and
/// defines `fuzzing_translator`, the translator's `init` as a plain function.
#[macro_export]
macro_rules! translator {
    ($translator:ty) => {
        #[cfg(not(fuzzing))]
        #[doc(hidden)]
        struct __SubsumeTranslatorExport;

        #[cfg(not(fuzzing))]
        ::std::thread_local! {
            static __SUBSUME_TRANSLATOR: ::core::cell::RefCell<::core::option::Option<$translator>> =
                const { ::core::cell::RefCell::new(::core::option::Option::None) };
        }

        #[cfg(not(fuzzing))]
        impl $crate::translator_bindings::Guest for __SubsumeTranslatorExport {
            fn init(
                params: ::std::vec::Vec<$crate::translator_bindings::subsume::robot::types::Param>,
            ) -> ::core::result::Result<(), ::std::string::String> {
                let params = $crate::Params(
                    params.into_iter().map(|p| $crate::Param { name: p.name, value: p.value }).collect(),
                );
                let state = <$translator as $crate::Translator>::init(&params)?;
                __SUBSUME_TRANSLATOR.with(|cell| *cell.borrow_mut() = ::core::option::Option::Some(state));
                ::core::result::Result::Ok(())
            }
            fn encode(command: ::std::string::String) -> ::core::result::Result<::std::vec::Vec<u8>, ::std::string::String> {
                __SUBSUME_TRANSLATOR.with(|cell| match cell.borrow_mut().as_mut() {
                    ::core::option::Option::Some(state) => $crate::Translator::encode(state, &command),
                    ::core::option::Option::None => ::core::result::Result::Err("encode called before init".into()),
                })
            }
            fn link() -> $crate::LinkPlan {
                __SUBSUME_TRANSLATOR.with(|cell| match cell.borrow().as_ref() {
                    ::core::option::Option::Some(state) => $crate::Translator::link(state),
                    ::core::option::Option::None => $crate::LinkPlan {
                        opening: ::std::vec::Vec::new(),
                        poll_period_ms: 0,
                        closing: ::std::vec::Vec::new(),
                    },
                })
            }
            fn poll(now_ns: u64) -> ::std::vec::Vec<u8> {
                __SUBSUME_TRANSLATOR.with(|cell| match cell.borrow_mut().as_mut() {
                    ::core::option::Option::Some(state) => $crate::Translator::poll(state, now_ns),
                    ::core::option::Option::None => ::std::vec::Vec::new(),
                })
            }
            fn decode(bytes: ::std::vec::Vec<u8>) -> $crate::Decoded {
                __SUBSUME_TRANSLATOR.with(|cell| match cell.borrow_mut().as_mut() {
                    ::core::option::Option::Some(state) => {
                        let decoded = $crate::Translator::decode(state, &bytes);
                        if let ::core::option::Option::Some(text) = $crate::Translator::fault(state) {
                            $crate::report_fault(&text);
                        }
                        decoded
                    }
                    ::core::option::Option::None => $crate::Decoded { feedback: ::std::vec::Vec::new(), malformed: 0 },
                })
            }
        }

        #[cfg(not(fuzzing))]
        $crate::translator_bindings::__export_translator!(__SubsumeTranslatorExport with_types_in $crate::translator_bindings);

        /// The translator built natively, for the fuzz targets (`fuzz/`,
        /// built with `--cfg fuzzing`), which include the translator's
        /// source and feed its decoder bytes with no component around it.
        #[cfg(fuzzing)]
        pub fn fuzzing_translator(
            params: &$crate::Params,
        ) -> ::core::result::Result<impl $crate::Translator + use<>, ::std::string::String> {
            <$translator as $crate::Translator>::init(params)
        }
    };
}

/// What a task's scoring component implements (the `scorer` world): the
/// score of one run from its recorded samples. It sees nothing else (no
/// host functions; its clocks stand still), so the same run scores the
/// same bits everywhere.
pub trait Scorer {
    /// The run's score and named sub-scores (each finite; names
    /// `[a-z0-9_.-]`, 1 to 64); `Err` when it cannot be scored.
    fn score(episode: &Episode) -> Result<Verdict, String>;
}

/// Exports `$scorer` (a type implementing [`Scorer`]) as the component's
/// implementation of the `subsume:robot/scorer` world.
#[macro_export]
macro_rules! scorer {
    ($scorer:ty) => {
        #[doc(hidden)]
        struct __SubsumeScorerExport;

        impl $crate::scorer_bindings::Guest for __SubsumeScorerExport {
            fn score(
                episode: $crate::Episode,
            ) -> ::core::result::Result<$crate::Verdict, ::std::string::String> {
                <$scorer as $crate::Scorer>::score(&episode)
            }
        }

        $crate::scorer_bindings::__export_scorer!(__SubsumeScorerExport with_types_in $crate::scorer_bindings);
    };
}

//! The envelope's decision: pure, with explicit time, table-tested.
//!
//! [`Envelope::decide`] takes the command the arbiter chose and returns what
//! may reach the motors, with the reason for any change. It only passes,
//! scales down or stops: every output is the input with its linear and
//! angular speeds multiplied by factors in `[0, 1]` (one common factor
//! whenever the arc's curvature is kept), and a GOTO (a planner's goal, not
//! a motion) becomes STOP.
//!
//! Checks, in order of severity:
//! - stale sensors: the ranges (or the pose) are older than `stale`, or
//!   never came: STOP; likewise a wired camera's pictures older than
//!   `camera_stale` (a camera that stops sending, e.g. behind a vision
//!   component that steers by it);
//! - the stop zone: along the commanded arc, the footprint (a disc of
//!   `radius`) would touch a range point within `stop_distance`: the
//!   linear speed stops (turning in place, which a disc cannot collide
//!   with, passes);
//! - the geofence: the footprint's leading edge plus `stop_distance`
//!   would leave the polygon (or the robot is outside and the move does
//!   not bring it back): the linear speed stops;
//! - the slowdown zone: within `slow_distance` the speed is capped,
//!   falling linearly from `max_speed` at the zone's edge to 0 at the stop
//!   zone; the time to collision at the commanded speed must be at least
//!   `ttc_s`;
//! - speed and turn-rate limits (`max_speed`, `max_reverse`, `max_turn`);
//! - acceleration limits: speeds may grow by at most `max_accel` /
//!   `max_turn_accel` per second; slowing down is never delayed.
//!
//! The zones budget the robot's reaction: a scan shows where things were
//! when it arrived, and the next judgment comes one control interval later.
//! The distance covered meanwhile (the last output's speed times the scan's
//! age, plus the commanded speed times the longest recent interval between
//! judgments, see [`REACTION_WINDOW_NS`]) is taken off every clearance
//! before the zones are applied. On a busy machine, where cycles come late,
//! the robot therefore slows and stops earlier, not later.

use std::collections::BTreeMap;
use std::fmt;

use serde::Serialize;

use crate::contract::control::ControlCommand;

/// Step of the march along the commanded arc: the collision monitor's
/// resolution. Contact is reported one step early, never late.
pub const MARCH_STEP_M: f64 = 0.01;
/// Longest look ahead along the arc: bounds the monitor's work per command
/// whatever speed or time-to-collision a file asks for.
pub const MAX_LOOKAHEAD_M: f64 = 5.0;
/// Longest interval the acceleration limit credits: a silence (no command
/// for seconds) must not license a jump to full speed.
pub const MAX_ACCEL_INTERVAL_S: f64 = 0.1;
/// Most geofence corners: bounds the point-in-polygon work per command.
pub const MAX_FENCE_POINTS: usize = 64;
/// Spacing of the points assumed between two adjacent rays (at the nearer
/// of their readings): a corner between two rays is not missed.
pub const GAP_SPACING_M: f64 = 0.05;
/// Most points assumed in one gap: bounds the work of a wide, far gap.
pub const MAX_GAP_POINTS: usize = 8;
/// How long a range point stays remembered (in odometry coordinates, when
/// the pose is wired): a thin obstacle seen by one ray and then lost between
/// rays, or one the robot turned away from, is still avoided.
pub const MEMORY_NS: u64 = 3_000_000_000;
/// Only points this close (m) are remembered: farther ones cannot be
/// reached before the next scans.
pub const MEMORY_RANGE_M: f64 = 1.5;
/// Remembered points are kept one per cell of this size (m).
pub const MEMORY_CELL_M: f64 = 0.02;
/// Most remembered points: bounds the memory and the work per command
/// whatever the scans contain.
pub const MAX_MEMORY_POINTS: usize = 512;
/// How long the longest interval between two judgments is remembered: a
/// machine that ran late recently is assumed to run late again.
pub const REACTION_WINDOW_NS: u64 = 5_000_000_000;
/// Longest interval budgeted as reaction time, s: beyond it the sensors are
/// stale anyway (and a stall of seconds is the stall watchdog's case), so a
/// single long pause cannot freeze the robot for the whole window.
pub const MAX_REACTION_S: f64 = 0.5;
/// Most range readings read per scan (the motor protocols' own bound).
pub const MAX_RANGES: usize = crate::robot::protocol::MAX_RANGES;

/// The owner's envelope, in SI units.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Settings {
    /// Fastest forward speed, m/s.
    pub max_speed: f64,
    /// Fastest reverse speed, m/s (the rays may not see behind).
    pub max_reverse: f64,
    /// Fastest turn, rad/s.
    pub max_turn: f64,
    /// Largest increase of the linear speed, m/s².
    pub max_accel: f64,
    /// Largest increase of the turn rate, rad/s².
    pub max_turn_accel: f64,
    /// The footprint: a disc of this radius around the range sensor, m.
    pub radius: f64,
    /// Clearance below which linear motion stops, m.
    pub stop_distance: f64,
    /// Clearance below which speed is capped, m.
    pub slow_distance: f64,
    /// Least time to collision at the commanded speed, s.
    pub ttc_s: f64,
    /// Angle covered by the range rays (right to left, centred on the heading).
    pub fov: f64,
    /// Ranges or pose older than this stop the robot, ns.
    pub stale_ns: u64,
    /// The polygon in odometry coordinates the robot may not leave (empty:
    /// none).
    pub geofence: Vec<[f64; 2]>,
    /// Whether ranges are wired in: without them the collision monitor is
    /// off, and their staleness not checked.
    pub watch_ranges: bool,
    /// Whether the pose is wired in (required by a geofence).
    pub watch_pose: bool,
    /// Whether a camera's pictures are wired in: then they must keep
    /// coming, at most `camera_stale_ns` apart.
    pub watch_camera: bool,
    /// A wired camera's pictures older than this stop the robot, ns.
    pub camera_stale_ns: u64,
}

/// What the envelope did to a command.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Action {
    Passed,
    Scaled,
    Stopped,
}

/// Why the envelope changed a command, with the reading behind it.
#[derive(Clone, Debug, PartialEq)]
pub enum Cause {
    /// No ranges for `age_s` (None: never).
    StaleRanges {
        age_s: Option<f64>,
    },
    /// No pose for `age_s` (None: never).
    StalePose {
        age_s: Option<f64>,
    },
    /// No picture from the wired camera for `age_s` (None: never).
    StaleCamera {
        age_s: Option<f64>,
    },
    /// A GOTO reached the envelope: goals are for planners.
    Goto,
    /// An obstacle `ahead` m along the path, inside the stop zone.
    StopZone {
        ahead: f64,
        zone: f64,
    },
    /// Moving would leave the geofence (`edge` m to its border).
    Geofence {
        edge: f64,
        outside: bool,
    },
    /// An obstacle `ahead` m along the path, inside the slowdown zone.
    SlowZone {
        ahead: f64,
        zone: f64,
        cap: f64,
    },
    /// Time to collision at the commanded speed below the limit.
    TimeToCollision {
        ahead: f64,
        ttc_s: f64,
        limit_s: f64,
    },
    SpeedLimit {
        limit: f64,
    },
    ReverseLimit {
        limit: f64,
    },
    TurnLimit {
        limit: f64,
    },
    Acceleration {
        linear: f64,
        angular: f64,
    },
}

impl fmt::Display for Cause {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let age = |age: &Option<f64>| age.map_or("never received".to_string(), |a| format!("none for {a:.2} s"));
        match self {
            Cause::StaleRanges { age_s } => write!(f, "ranges stale ({})", age(age_s)),
            Cause::StalePose { age_s } => write!(f, "pose stale ({})", age(age_s)),
            Cause::StaleCamera { age_s } => write!(f, "camera stale ({})", age(age_s)),
            Cause::Goto => write!(f, "GOTO is a goal for a planner, not a motion"),
            Cause::StopZone { ahead, zone } => write!(f, "obstacle {ahead:.2} m ahead, stop zone {zone:.2} m"),
            Cause::Geofence { edge, outside: false } => write!(f, "geofence: edge {edge:.2} m away"),
            Cause::Geofence { edge, outside: true } => {
                write!(f, "geofence: outside by {edge:.2} m, only moves back inside pass")
            }
            Cause::SlowZone { ahead, zone, cap } => {
                write!(f, "obstacle {ahead:.2} m ahead, slowdown zone {zone:.2} m: at most {cap:.2} m/s")
            }
            Cause::TimeToCollision { ahead, ttc_s, limit_s } => {
                write!(f, "obstacle {ahead:.2} m ahead, time to collision {ttc_s:.2} s < {limit_s:.2} s")
            }
            Cause::SpeedLimit { limit } => write!(f, "speed limit {limit} m/s"),
            Cause::ReverseLimit { limit } => write!(f, "reverse speed limit {limit} m/s"),
            Cause::TurnLimit { limit } => write!(f, "turn-rate limit {limit} rad/s"),
            Cause::Acceleration { linear, angular } => {
                write!(f, "acceleration limits {linear} m/s² and {angular} rad/s²")
            }
        }
    }
}

impl Cause {
    /// The reading behind the cause, as numbers with their units in the
    /// field names (what the `interventions` output carries; `None` for a
    /// sensor never received).
    pub fn reading(&self) -> serde_json::Value {
        use serde_json::json;
        match self {
            Cause::StaleRanges { age_s } | Cause::StalePose { age_s } | Cause::StaleCamera { age_s } => {
                json!({ "age_s": age_s })
            }
            Cause::Goto => json!({}),
            Cause::StopZone { ahead, zone } => json!({ "ahead_m": ahead, "zone_m": zone }),
            Cause::Geofence { edge, outside } => json!({ "edge_m": edge, "outside": outside }),
            Cause::SlowZone { ahead, zone, cap } => json!({ "ahead_m": ahead, "zone_m": zone, "cap_m_s": cap }),
            Cause::TimeToCollision { ahead, ttc_s, limit_s } => {
                json!({ "ahead_m": ahead, "ttc_s": ttc_s, "limit_s": limit_s })
            }
            Cause::SpeedLimit { limit } | Cause::ReverseLimit { limit } => json!({ "limit_m_s": limit }),
            Cause::TurnLimit { limit } => json!({ "limit_rad_s": limit }),
            Cause::Acceleration { linear, angular } => json!({ "linear_m_s2": linear, "angular_rad_s2": angular }),
        }
    }

    /// A short name, for counts in the report.
    pub fn kind(&self) -> &'static str {
        match self {
            Cause::StaleRanges { .. } => "stale-ranges",
            Cause::StalePose { .. } => "stale-pose",
            Cause::StaleCamera { .. } => "stale-camera",
            Cause::Goto => "goto",
            Cause::StopZone { .. } => "stop-zone",
            Cause::Geofence { .. } => "geofence",
            Cause::SlowZone { .. } => "slowdown-zone",
            Cause::TimeToCollision { .. } => "time-to-collision",
            Cause::SpeedLimit { .. } => "speed-limit",
            Cause::ReverseLimit { .. } => "reverse-limit",
            Cause::TurnLimit { .. } => "turn-limit",
            Cause::Acceleration { .. } => "acceleration",
        }
    }
}

/// The envelope's answer to one command.
#[derive(Clone, Debug, PartialEq)]
pub struct Verdict {
    /// What goes to the motors.
    pub command: ControlCommand,
    pub action: Action,
    /// Why it was changed (None when passed).
    pub cause: Option<Cause>,
}

/// The latest scan, as points in the robot's frame (x ahead, y left).
#[derive(Clone, Debug, Default)]
struct Scan {
    points: Vec<[f64; 2]>,
    at_ns: u64,
}

/// The envelope's state: the latest sensor data and the last output.
#[derive(Clone, Debug)]
pub struct Envelope {
    settings: Settings,
    scan: Option<Scan>,
    pose: Option<([f64; 3], u64)>,
    /// When the wired camera's last picture came.
    camera_at: Option<u64>,
    /// Range points seen recently, in odometry coordinates, one per cell:
    /// (point, seen at).
    memory: BTreeMap<(i64, i64), ([f64; 2], u64)>,
    /// The last (linear, angular) sent and when.
    last_out: (f64, f64),
    last_out_at: Option<u64>,
    /// When the last judgment ran, and the longest interval between two
    /// judgments within [`REACTION_WINDOW_NS`] (interval, seen at).
    last_judged_at: Option<u64>,
    worst_interval: (u64, u64),
}

impl Envelope {
    pub fn new(settings: Settings) -> Envelope {
        Envelope {
            settings,
            scan: None,
            pose: None,
            camera_at: None,
            memory: BTreeMap::new(),
            last_out: (0.0, 0.0),
            last_out_at: None,
            last_judged_at: None,
            worst_interval: (0, 0),
        }
    }

    /// Notes a judgment at `now_ns`, for the reaction time.
    fn note_judgment(&mut self, now_ns: u64) {
        if let Some(last) = self.last_judged_at {
            let interval = now_ns.saturating_sub(last);
            let (worst, seen_at) = self.worst_interval;
            if interval >= worst || now_ns.saturating_sub(seen_at) > REACTION_WINDOW_NS {
                self.worst_interval = (interval, now_ns);
            }
        }
        self.last_judged_at = Some(now_ns.max(self.last_judged_at.unwrap_or(0)));
    }

    /// The reaction time budgeted now, s: the longest recent interval
    /// between judgments, at most [`MAX_REACTION_S`].
    pub fn reaction_s(&self) -> f64 {
        (self.worst_interval.0 as f64 / 1e9).min(MAX_REACTION_S)
    }

    pub fn settings(&self) -> &Settings {
        &self.settings
    }

    /// A scan: readings in metres from the sensor at the footprint's
    /// centre, spread evenly over `fov` from right to left. Readings that
    /// are not finite and positive are skipped. Between two adjacent rays
    /// the nearer reading is assumed across the gap (a point every
    /// [`GAP_SPACING_M`]), so a corner between rays is seen.
    pub fn ranges(&mut self, ranges: &[f64], now_ns: u64) {
        let n = ranges.len().min(MAX_RANGES);
        let (first, step) =
            if n > 1 { (-self.settings.fov / 2.0, self.settings.fov / (n - 1) as f64) } else { (0.0, 0.0) };
        let valid = |r: f64| r.is_finite() && r > 0.0;
        let mut points = Vec::with_capacity(n * (1 + MAX_GAP_POINTS));
        self.memory.retain(|_, (_, at)| now_ns.saturating_sub(*at) <= MEMORY_NS);
        for (i, &r) in ranges.iter().take(n).enumerate() {
            let a = first + step * i as f64;
            if valid(r) {
                points.push([r * a.cos(), r * a.sin()]);
                if r <= MEMORY_RANGE_M {
                    self.remember_point([r * a.cos(), r * a.sin()], now_ns);
                }
            }
            // The gap to the next ray, at the nearer reading.
            if let Some(&next) = ranges.get(i + 1).filter(|_| i + 1 < n) {
                let near = if valid(r) && valid(next) { r.min(next) } else { continue };
                let extra = ((near * step / GAP_SPACING_M).ceil() as usize).saturating_sub(1).min(MAX_GAP_POINTS);
                for k in 1..=extra {
                    let b = a + step * k as f64 / (extra + 1) as f64;
                    points.push([near * b.cos(), near * b.sin()]);
                }
            }
        }
        self.scan = Some(Scan { points, at_ns: now_ns });
    }

    /// Remembers `point` (robot frame) in odometry coordinates, if the pose
    /// is known.
    fn remember_point(&mut self, point: [f64; 2], now_ns: u64) {
        let Some(([x, y, h], _)) = self.pose else { return };
        let (sin, cos) = h.sin_cos();
        let world = [x + point[0] * cos - point[1] * sin, y + point[0] * sin + point[1] * cos];
        let cell = ((world[0] / MEMORY_CELL_M).floor() as i64, (world[1] / MEMORY_CELL_M).floor() as i64);
        if !self.memory.contains_key(&cell) && self.memory.len() >= MAX_MEMORY_POINTS {
            // Full: the oldest point makes room.
            let oldest = self.memory.iter().min_by_key(|(_, (_, at))| *at).map(|(k, _)| *k);
            if let Some(oldest) = oldest {
                self.memory.remove(&oldest);
            }
        }
        self.memory.insert(cell, (world, now_ns));
    }

    /// The remembered points in the robot's frame at the current pose,
    /// within `reach` m.
    fn remembered(&self, reach: f64) -> Vec<[f64; 2]> {
        let Some(([x, y, h], _)) = self.pose else { return Vec::new() };
        let (sin, cos) = h.sin_cos();
        self.memory
            .values()
            .map(|(p, _)| {
                let (dx, dy) = (p[0] - x, p[1] - y);
                [dx * cos + dy * sin, -dx * sin + dy * cos]
            })
            .filter(|p| p[0].hypot(p[1]) <= reach)
            .collect()
    }

    /// The odometry pose `[x, y, heading]`; anything else is ignored.
    /// Notes a picture from the wired camera at `now_ns`.
    pub fn picture(&mut self, now_ns: u64) {
        self.camera_at = Some(now_ns);
    }

    pub fn pose(&mut self, pose: &[f64], now_ns: u64) -> bool {
        match pose {
            [x, y, h, ..] if x.is_finite() && y.is_finite() && h.is_finite() => {
                self.pose = Some(([*x, *y, *h], now_ns));
                true
            }
            _ => false,
        }
    }

    /// The smallest clearance between the footprint and a range point, m.
    pub fn closest(&self) -> Option<f64> {
        let scan = self.scan.as_ref()?;
        scan.points.iter().map(|p| p[0].hypot(p[1]) - self.settings.radius).reduce(f64::min)
    }

    /// What may reach the motors for `command` at `now_ns`; the output is
    /// remembered for the acceleration limit.
    pub fn decide(&mut self, command: ControlCommand, now_ns: u64) -> Verdict {
        self.note_judgment(now_ns);
        let verdict = self.judge(command, now_ns);
        self.remember(&verdict, now_ns);
        verdict
    }

    /// Judges `command` again at `now_ns` (new sensor data, a tick) and
    /// returns the verdict only if it is more restrictive than the last
    /// output (slower on one axis and faster on none): a review never
    /// starts or speeds up motion.
    pub fn review(&mut self, command: ControlCommand, now_ns: u64) -> Option<Verdict> {
        self.note_judgment(now_ns);
        let verdict = self.judge(command, now_ns);
        let (v, w) = speeds(&verdict.command);
        let (lv, lw) = self.last_out;
        let slower = v.abs() < lv.abs() || w.abs() < lw.abs();
        let faster = v.abs() > lv.abs() || w.abs() > lw.abs();
        if slower && !faster {
            self.remember(&verdict, now_ns);
            Some(verdict)
        } else {
            None
        }
    }

    fn remember(&mut self, verdict: &Verdict, now_ns: u64) {
        self.last_out = speeds(&verdict.command);
        self.last_out_at = Some(now_ns);
    }

    fn judge(&self, command: ControlCommand, now_ns: u64) -> Verdict {
        let (v, w) = match command {
            ControlCommand::Stop => return Verdict { command, action: Action::Passed, cause: None },
            ControlCommand::Goto { .. } => return stop(Cause::Goto),
            ControlCommand::Vel { linear, angular } => (linear, angular),
        };
        if v == 0.0 && w == 0.0 {
            return Verdict { command, action: Action::Passed, cause: None };
        }
        let s = &self.settings;
        let age = |at: u64| now_ns.saturating_sub(at);
        if s.watch_ranges {
            match &self.scan {
                None => return stop(Cause::StaleRanges { age_s: None }),
                Some(scan) if age(scan.at_ns) > s.stale_ns => {
                    return stop(Cause::StaleRanges { age_s: Some(age(scan.at_ns) as f64 / 1e9) });
                }
                Some(_) => {}
            }
        }
        if s.watch_pose {
            match &self.pose {
                None => return stop(Cause::StalePose { age_s: None }),
                Some((_, at)) if age(*at) > s.stale_ns => {
                    return stop(Cause::StalePose { age_s: Some(age(*at) as f64 / 1e9) });
                }
                Some(_) => {}
            }
        }
        if s.watch_camera {
            match self.camera_at {
                None => return stop(Cause::StaleCamera { age_s: None }),
                Some(at) if age(at) > s.camera_stale_ns => {
                    return stop(Cause::StaleCamera { age_s: Some(age(at) as f64 / 1e9) });
                }
                Some(_) => {}
            }
        }

        // One common factor keeps the arc; the binding limit names the cause.
        let mut factor = 1.0;
        let mut cause = None;
        let mut limit = |k: f64, c: Cause| {
            if k < factor {
                factor = k.max(0.0);
                cause = Some(c);
            }
        };
        let mut linear_stop: Option<Cause> = None;
        if v != 0.0 {
            if let Some(scan) = &self.scan {
                // The distance covered before this judgment can take effect.
                let scan_age_s = age(scan.at_ns).min(s.stale_ns) as f64 / 1e9;
                let margin = self.last_out.0.abs() * scan_age_s + v.abs() * self.reaction_s();
                let lookahead = (s.slow_distance.max(v.abs() * s.ttc_s) + margin + MARCH_STEP_M).min(MAX_LOOKAHEAD_M);
                let mut points = self.remembered(lookahead + s.radius);
                points.extend_from_slice(&scan.points);
                if let Some(ahead) = path_clearance(&points, s.radius, v, w, lookahead) {
                    // What is left once the robot has reacted.
                    let left = ahead - margin;
                    if left <= s.stop_distance {
                        linear_stop = Some(Cause::StopZone { ahead, zone: s.stop_distance + margin });
                    } else {
                        if left <= s.slow_distance && s.slow_distance > s.stop_distance {
                            let cap = s.max_speed * (left - s.stop_distance) / (s.slow_distance - s.stop_distance);
                            limit(cap / v.abs(), Cause::SlowZone { ahead, zone: s.slow_distance + margin, cap });
                        }
                        let ttc = left / v.abs();
                        if ttc < s.ttc_s {
                            limit(ttc / s.ttc_s, Cause::TimeToCollision { ahead, ttc_s: ttc, limit_s: s.ttc_s });
                        }
                    }
                }
            }
            if linear_stop.is_none()
                && let (false, Some((pose, _))) = (s.geofence.is_empty(), &self.pose)
            {
                linear_stop = fence_check(&s.geofence, *pose, v.signum() * (s.radius + s.stop_distance));
            }
            if v > s.max_speed {
                limit(s.max_speed / v, Cause::SpeedLimit { limit: s.max_speed });
            }
            if -v > s.max_reverse {
                limit(s.max_reverse / -v, Cause::ReverseLimit { limit: s.max_reverse });
            }
        }
        if w.abs() > s.max_turn {
            limit(s.max_turn / w.abs(), Cause::TurnLimit { limit: s.max_turn });
        }
        let (mut v_out, mut w_out) =
            if linear_stop.is_some() { (0.0, w.clamp(-s.max_turn, s.max_turn)) } else { (v * factor, w * factor) };

        // Acceleration: growth is limited, slowing down never is.
        let dt = self.last_out_at.map_or(MAX_ACCEL_INTERVAL_S, |at| (age(at) as f64 / 1e9).min(MAX_ACCEL_INTERVAL_S));
        let (lv, lw) = self.last_out;
        let room = |out: f64, last: f64, accel: f64| {
            let base = if out * last > 0.0 { last.abs() } else { 0.0 };
            base + accel * dt
        };
        let room_v = room(v_out, lv, s.max_accel);
        let room_w = room(w_out, lw, s.max_turn_accel);
        let k = [(v_out, room_v), (w_out, room_w)]
            .iter()
            .filter(|(out, room)| out.abs() > *room)
            .map(|(out, room)| room / out.abs())
            .fold(1.0_f64, f64::min);
        if k < 1.0 {
            v_out *= k;
            w_out *= k;
            if linear_stop.is_none() {
                cause = Some(Cause::Acceleration { linear: s.max_accel, angular: s.max_turn_accel });
            }
        }

        if let Some(c) = linear_stop {
            let command =
                if w_out == 0.0 { ControlCommand::Stop } else { ControlCommand::Vel { linear: 0.0, angular: w_out } };
            return Verdict { command, action: Action::Stopped, cause: Some(c) };
        }
        if v_out == v && w_out == w {
            return Verdict { command, action: Action::Passed, cause: None };
        }
        let (command, action) = if v_out == 0.0 && w_out == 0.0 {
            (ControlCommand::Stop, Action::Stopped)
        } else {
            (ControlCommand::Vel { linear: v_out, angular: w_out }, Action::Scaled)
        };
        Verdict { command, action, cause }
    }
}

fn stop(cause: Cause) -> Verdict {
    Verdict { command: ControlCommand::Stop, action: Action::Stopped, cause: Some(cause) }
}

fn speeds(command: &ControlCommand) -> (f64, f64) {
    match command {
        ControlCommand::Vel { linear, angular } => (*linear, *angular),
        _ => (0.0, 0.0),
    }
}

/// How far (m, along the path) the disc of `radius` may move on the arc of
/// (`v`, `w`) before it touches a point it is approaching, looking `lookahead`
/// m ahead; None when nothing is in the way. Points already inside the
/// footprint count only when the motion brings the disc closer to them.
pub fn path_clearance(points: &[[f64; 2]], radius: f64, v: f64, w: f64, lookahead: f64) -> Option<f64> {
    if v == 0.0 || points.is_empty() {
        return None;
    }
    let r2 = radius * radius;
    if w.abs() < 1e-9 {
        // Straight on: exact. A point at lateral offset y is met where the
        // disc's centre is sqrt(r² - y²) short of it.
        let sign = v.signum();
        return points
            .iter()
            .filter(|p| p[1].abs() < radius && sign * p[0] > 0.0)
            .map(|p| (sign * p[0] - (r2 - p[1] * p[1]).sqrt()).max(0.0))
            .filter(|s| *s <= lookahead)
            .reduce(f64::min);
    }
    let speed = v.abs();
    let steps = (lookahead / MARCH_STEP_M).ceil().max(1.0) as usize;
    // Only points the disc can reach within the look-ahead matter.
    let reach2 = (lookahead + radius).powi(2);
    let (points, start): (Vec<[f64; 2]>, Vec<f64>) =
        points.iter().map(|p| (*p, p[0] * p[0] + p[1] * p[1])).filter(|(_, d2)| *d2 <= reach2).unzip();
    if points.is_empty() {
        return None;
    }
    for step in 1..=steps {
        let s = step as f64 * MARCH_STEP_M;
        let t = s / speed;
        let (x, y) = if w.abs() < 1e-9 {
            (v * t, 0.0)
        } else {
            let r = v / w;
            (r * (w * t).sin(), r * (1.0 - (w * t).cos()))
        };
        let hit = points.iter().zip(&start).any(|(p, d0)| {
            let d = (p[0] - x).powi(2) + (p[1] - y).powi(2);
            d < r2 && d < *d0
        });
        if hit {
            return Some((s - MARCH_STEP_M).max(0.0));
        }
    }
    None
}

/// Whether moving `reach` m along the heading (negative: backwards) from
/// `pose` keeps the point inside `fence`; the cause to stop when not.
fn fence_check(fence: &[[f64; 2]], pose: [f64; 3], reach: f64) -> Option<Cause> {
    let [x, y, h] = pose;
    let here = [x, y];
    let there = [x + reach * h.cos(), y + reach * h.sin()];
    let inside_here = inside(fence, here);
    if inside(fence, there) {
        return None;
    }
    if inside_here {
        return Some(Cause::Geofence { edge: edge_distance(fence, here), outside: false });
    }
    let (now, then) = (edge_distance(fence, here), edge_distance(fence, there));
    (then >= now).then_some(Cause::Geofence { edge: now, outside: true })
}

/// Point in polygon (even-odd rule).
pub fn inside(polygon: &[[f64; 2]], p: [f64; 2]) -> bool {
    let n = polygon.len();
    let mut inside = false;
    for i in 0..n {
        let a = polygon[i];
        let b = polygon[(i + 1) % n];
        if (a[1] > p[1]) != (b[1] > p[1]) {
            let x = a[0] + (p[1] - a[1]) * (b[0] - a[0]) / (b[1] - a[1]);
            if p[0] < x {
                inside = !inside;
            }
        }
    }
    inside
}

/// Distance from `p` to the polygon's border.
pub fn edge_distance(polygon: &[[f64; 2]], p: [f64; 2]) -> f64 {
    let n = polygon.len();
    (0..n)
        .map(|i| {
            let (a, b) = (polygon[i], polygon[(i + 1) % n]);
            let (dx, dy) = (b[0] - a[0], b[1] - a[1]);
            let len2 = dx * dx + dy * dy;
            let t = if len2 > 0.0 { (((p[0] - a[0]) * dx + (p[1] - a[1]) * dy) / len2).clamp(0.0, 1.0) } else { 0.0 };
            (p[0] - a[0] - t * dx).hypot(p[1] - a[1] - t * dy)
        })
        .fold(f64::INFINITY, f64::min)
}

#[cfg(test)]
mod tests {
    use super::*;

    const MS: u64 = 1_000_000;

    fn settings() -> Settings {
        Settings {
            max_speed: 0.5,
            max_reverse: 0.1,
            max_turn: 2.0,
            max_accel: 100.0,
            max_turn_accel: 100.0,
            radius: 0.2,
            stop_distance: 0.1,
            slow_distance: 0.4,
            ttc_s: 1.0,
            fov: std::f64::consts::PI,
            stale_ns: 500 * MS,
            geofence: Vec::new(),
            watch_ranges: true,
            watch_pose: false,
            watch_camera: false,
            camera_stale_ns: 1000 * MS,
        }
    }

    fn vel(linear: f64, angular: f64) -> ControlCommand {
        ControlCommand::Vel { linear, angular }
    }

    /// Three rays (right, ahead, left) with the one ahead at `ahead` m.
    fn scan_ahead(ahead: f64) -> Vec<f64> {
        vec![4.0, ahead, 4.0]
    }

    fn close(a: f64, b: f64) -> bool {
        (a - b).abs() < 1e-6
    }

    #[test]
    fn zones_and_time_to_collision_scale_or_stop_by_the_reading() {
        // (ray ahead m, command, expected output, action, cause kind);
        // radius 0.2, so clearance = reading - 0.2 (within one march step).
        #[rustfmt::skip]
        let table: Vec<(f64, ControlCommand, ControlCommand, Action, Option<&str>)> = vec![
            (4.0,  vel(0.3, 0.0),  vel(0.3, 0.0),  Action::Passed,  None),
            // clearance 0.28 (one step early: 0.27): cap 0.5 * 0.17 / 0.3 = 0.283
            // clearance 0.2: cap 0.5 * (0.2 - 0.1) / (0.4 - 0.1)
            (0.4,  vel(0.3, 0.0),  vel(0.5 / 3.0, 0.0), Action::Scaled, Some("slowdown-zone")),
            // clearance 1.0: 2 s to collision at 0.5 m/s, fine; clearance 0.4: 0.8 s < 1 s
            (1.2,  vel(0.5, 0.0),  vel(0.5, 0.0),  Action::Passed,  None),
            (0.6,  vel(0.5, 0.0),  vel(0.4, 0.0),  Action::Scaled,  Some("time-to-collision")),
            // inside the stop zone: linear stops, turning in place passes
            (0.28, vel(0.3, 0.0),  ControlCommand::Stop, Action::Stopped, Some("stop-zone")),
            (0.28, vel(0.3, 1.0),  vel(0.0, 1.0),  Action::Stopped, Some("stop-zone")),
            // backing away from it is fine (no ray behind), within max-reverse
            (0.28, vel(-0.05, 0.0), vel(-0.05, 0.0), Action::Passed, None),
            (0.28, vel(-0.3, 0.0), vel(-0.1, 0.0), Action::Scaled,  Some("reverse-limit")),
            // turning in place never meets the collision monitor
            (0.21, vel(0.0, 1.5),  vel(0.0, 1.5),  Action::Passed,  None),
            // STOP always passes
            (0.21, ControlCommand::Stop, ControlCommand::Stop, Action::Passed, None),
        ];
        for (i, (ahead, command, expected, action, cause)) in table.into_iter().enumerate() {
            let mut envelope = Envelope::new(settings());
            envelope.ranges(&scan_ahead(ahead), 0);
            let verdict = envelope.decide(command, 10 * MS);
            let (ev, ew) = speeds(&expected);
            let (gv, gw) = speeds(&verdict.command);
            assert!(
                close(gv, ev)
                    && close(gw, ew)
                    && std::mem::discriminant(&verdict.command) == std::mem::discriminant(&expected),
                "row {i}: {command} -> {} (expected {expected})",
                verdict.command
            );
            assert_eq!(verdict.action, action, "row {i}");
            assert_eq!(verdict.cause.as_ref().map(Cause::kind), cause, "row {i}");
        }
    }

    #[test]
    fn the_intervention_names_the_reading_and_the_zone() {
        let mut envelope = Envelope::new(settings());
        envelope.ranges(&scan_ahead(0.28), 0);
        let verdict = envelope.decide(vel(0.45, 0.0), 0);
        assert_eq!(verdict.command, ControlCommand::Stop);
        assert_eq!(verdict.cause.map(|c| c.to_string()).as_deref(), Some("obstacle 0.08 m ahead, stop zone 0.10 m"));
    }

    #[test]
    fn arcs_see_what_a_straight_corridor_would_miss() {
        // An obstacle 0.5 m ahead and 0.4 m to the left: clear straight on,
        // in the way of a left arc.
        let points = [[0.5, 0.4]];
        assert_eq!(path_clearance(&points, 0.2, 0.3, 0.0, 1.0), None);
        let ahead = path_clearance(&points, 0.2, 0.3, 0.6, 1.0);
        assert!(ahead.is_some_and(|a| a > 0.2 && a < 0.6), "{ahead:?}");
        // Moving away from a point inside the footprint is allowed.
        assert_eq!(path_clearance(&[[-0.1, 0.0]], 0.2, 0.3, 0.0, 1.0), None);
        assert_eq!(path_clearance(&[[0.1, 0.0]], 0.2, 0.3, 0.0, 1.0), Some(0.0));
        // Straight on, exact: a point 0.5 ahead and 0.12 aside meets the
        // disc after 0.5 - 0.16.
        let exact = path_clearance(&[[0.5, 0.12]], 0.2, 0.3, 0.0, 1.0);
        assert!(exact.is_some_and(|a| close(a, 0.34)), "{exact:?}");
        // The march agrees with it within one step on a nearly straight arc.
        let marched = path_clearance(&[[0.5, 0.12]], 0.2, 0.3, 1e-6, 1.0);
        assert!(marched.is_some_and(|a| (a - 0.34).abs() <= MARCH_STEP_M + 1e-9), "{marched:?}");
    }

    #[test]
    fn speed_turn_and_acceleration_limits_scale_without_bending_the_arc() {
        let mut s = settings();
        s.watch_ranges = false;
        s.max_accel = 1.0;
        s.max_turn_accel = 4.0;
        let mut envelope = Envelope::new(s);
        // (ms, command, expected linear, expected angular, cause)
        #[rustfmt::skip]
        let table: Vec<(u64, ControlCommand, f64, f64, Option<&str>)> = vec![
            (0,   vel(0.4, 0.0), 0.1,  0.0, Some("acceleration")), // a start credits 100 ms
            (50,  vel(0.4, 0.0), 0.15, 0.0, Some("acceleration")), // 1 m/s² x 50 ms
            (100, vel(0.4, 0.0), 0.20, 0.0, Some("acceleration")),
            (5000, vel(0.4, 0.0), 0.30, 0.0, Some("acceleration")), // a silence credits at most 100 ms
            (5010, vel(0.1, 0.0), 0.10, 0.0, None),                // slowing down passes at once
            (5020, vel(-0.1, 0.0), -0.01, 0.0, Some("acceleration")), // reversing starts from zero
            (5030, vel(0.0, 3.0), 0.0, 0.04, Some("acceleration")),   // 4 rad/s² x 10 ms
            (5130, vel(0.0, 3.0), 0.0, 0.44, Some("acceleration")),
            (9000, vel(0.0, 3.0), 0.0, 0.84, Some("acceleration")),
            (9100, vel(0.0, 3.0), 0.0, 1.24, Some("acceleration")),
            (9200, vel(0.0, 3.0), 0.0, 1.64, Some("acceleration")),
            (9300, vel(0.0, 3.0), 0.0, 2.0, Some("turn-limit")),
            (9400, vel(1.0, 4.0), 0.1, 0.4, Some("acceleration")),    // the arc (curvature 4) is kept
        ];
        for (ms, command, v, w, cause) in table {
            let verdict = envelope.decide(command, ms * MS);
            let (gv, gw) = speeds(&verdict.command);
            assert!(close(gv, v) && close(gw, w), "at {ms} ms: {command} -> {}", verdict.command);
            assert_eq!(verdict.cause.as_ref().map(Cause::kind), cause, "at {ms} ms");
        }
        // The speed limit binds when acceleration does not.
        let mut s = settings();
        s.watch_ranges = false;
        let mut envelope = Envelope::new(s);
        envelope.decide(vel(0.0, 0.0), 0);
        let verdict = envelope.decide(vel(1.0, 1.0), 100 * MS);
        assert_eq!(verdict.command, vel(0.5, 0.5));
        assert_eq!(verdict.cause, Some(Cause::SpeedLimit { limit: 0.5 }));
    }

    /// A wired camera (e.g. behind a vision component that steers by it)
    /// is a sensor like the others: no picture yet, or none for longer
    /// than `camera_stale`, stops the robot; turning in place too, as for
    /// stale ranges. Unwired, it is not watched.
    #[test]
    fn a_wired_camera_that_stops_sending_stops_the_robot() {
        let kind = |v: &Verdict| v.cause.as_ref().map(Cause::kind);
        let mut s = settings();
        s.watch_camera = true;
        // (accelerations unbounded here: only the camera decides)
        (s.max_accel, s.max_turn_accel) = (100.0, 100.0);
        let mut envelope = Envelope::new(s.clone());
        envelope.ranges(&scan_ahead(4.0), 0);
        let v = envelope.decide(vel(0.1, 0.0), 0);
        assert_eq!((v.command, kind(&v)), (ControlCommand::Stop, Some("stale-camera")));
        assert_eq!(v.cause.map(|c| c.to_string()).as_deref(), Some("camera stale (never received)"));
        // (time goes on as the scans keep coming: only the camera is late)
        // (now ms, a picture then, the command's speeds, the cause expected)
        type Row = (u64, Option<u64>, (f64, f64), Option<&'static str>);
        let rows: &[Row] = &[
            (10, Some(10), (0.1, 0.0), None),
            (400, None, (0.1, 0.0), None),
            (1010, None, (0.1, 0.0), None),
            (1011, None, (0.1, 0.0), Some("stale-camera")),
            (1100, None, (0.0, 0.5), Some("stale-camera")),
            (1200, Some(1200), (0.1, 0.0), None),
        ];
        for &(ms, picture, (v, w), cause) in rows {
            envelope.ranges(&scan_ahead(4.0), ms * MS);
            if let Some(at) = picture {
                envelope.picture(at * MS);
            }
            let verdict = envelope.decide(vel(v, w), ms * MS);
            assert_eq!(kind(&verdict), cause, "at {ms} ms");
            assert_eq!(verdict.command == ControlCommand::Stop, cause.is_some(), "at {ms} ms: {}", verdict.command);
        }
        let mut late = Envelope::new(s.clone());
        late.ranges(&scan_ahead(4.0), 2500 * MS);
        late.picture(0);
        let v = late.decide(vel(0.1, 0.0), 2500 * MS);
        assert_eq!(v.cause.map(|c| c.to_string()).as_deref(), Some("camera stale (none for 2.50 s)"));
        s.watch_camera = false;
        let mut unwired = Envelope::new(s);
        unwired.ranges(&scan_ahead(4.0), 0);
        assert_eq!(unwired.decide(vel(0.1, 0.0), 0).action, Action::Passed);
    }

    #[test]
    fn stale_or_missing_sensors_stop_the_robot() {
        let mut s = settings();
        s.watch_pose = true;
        let mut envelope = Envelope::new(s);
        let kind = |v: &Verdict| v.cause.as_ref().map(Cause::kind);
        let v = envelope.decide(vel(0.1, 0.0), 0);
        assert_eq!((v.command, kind(&v)), (ControlCommand::Stop, Some("stale-ranges")));
        envelope.ranges(&scan_ahead(4.0), 0);
        let v = envelope.decide(vel(0.1, 0.0), 0);
        assert_eq!((v.command, kind(&v)), (ControlCommand::Stop, Some("stale-pose")));
        assert!(envelope.pose(&[1.0, 1.0, 0.0], 0));
        assert!(!envelope.pose(&[1.0, f64::NAN, 0.0], 0), "a bad pose is ignored");
        assert!(!envelope.pose(&[1.0], 0));
        assert_eq!(envelope.decide(vel(0.1, 0.0), 500 * MS).action, Action::Passed, "500 ms is not stale yet");
        let v = envelope.decide(vel(0.1, 0.0), 501 * MS);
        assert_eq!(v.command, ControlCommand::Stop);
        assert_eq!(v.cause.map(|c| c.to_string()).as_deref(), Some("ranges stale (none for 0.50 s)"));
        envelope.ranges(&scan_ahead(4.0), 600 * MS);
        let v = envelope.decide(vel(0.1, 0.0), 600 * MS);
        assert_eq!(kind(&v), Some("stale-pose"));
        // Unwired sensors are not watched.
        let mut s = settings();
        s.watch_ranges = false;
        let mut envelope = Envelope::new(s);
        assert_eq!(envelope.decide(vel(0.1, 0.0), 0).action, Action::Passed);
    }

    #[test]
    fn the_geofence_stops_moves_out_and_lets_moves_back_in() {
        let mut s = settings();
        s.watch_ranges = false;
        s.watch_pose = true;
        s.geofence = vec![[0.0, 0.0], [4.0, 0.0], [4.0, 3.0], [0.0, 3.0]];
        // (pose, command, stopped?) ; reach = radius + stop = 0.3 m
        #[rustfmt::skip]
        let table: Vec<([f64; 3], f64, Option<&str>)> = vec![
            ([2.0, 1.5, 0.0], 0.2, None),                        // in the middle
            ([3.6, 1.5, 0.0], 0.2, None),                        // 0.4 from the edge
            ([3.75, 1.5, 0.0], 0.2, Some("geofence")),            // heading out
            ([3.75, 1.5, std::f64::consts::PI], 0.2, None),       // heading in
            ([3.75, 1.5, std::f64::consts::PI], -0.1, Some("geofence")), // backing out
            ([4.5, 1.5, 0.0], 0.2, Some("geofence")),             // outside, moving further out
            ([4.5, 1.5, std::f64::consts::PI], 0.2, None),        // outside, coming back
        ];
        for (i, (pose, v, cause)) in table.into_iter().enumerate() {
            let mut envelope = Envelope::new(s.clone());
            envelope.pose(&pose, 0);
            envelope.decide(vel(v, 0.0), 0);
            let verdict = envelope.decide(vel(v, 0.0), 100 * MS);
            assert_eq!(verdict.cause.as_ref().map(Cause::kind), cause, "row {i}: {:?}", verdict.cause);
            if cause.is_some() {
                assert_eq!(verdict.command, ControlCommand::Stop, "row {i}");
            }
        }
        assert!(inside(&s.geofence, [1.0, 1.0]) && !inside(&s.geofence, [5.0, 1.0]));
        assert!(close(edge_distance(&s.geofence, [3.75, 1.5]), 0.25));
    }

    #[test]
    fn a_thin_obstacle_lost_between_rays_is_remembered_where_it_was_seen() {
        let mut s = settings();
        s.watch_pose = true;
        s.max_accel = 1000.0;
        let mut envelope = Envelope::new(s);
        // Seen 0.25 m ahead (in the stop zone) at pose (1, 1, 0)...
        envelope.pose(&[1.0, 1.0, 0.0], 0);
        envelope.ranges(&scan_ahead(0.25), 0);
        assert_eq!(envelope.decide(vel(0.3, 0.0), 0).command, ControlCommand::Stop);
        // ... then lost between the rays: still stopped.
        envelope.ranges(&scan_ahead(4.0), 100 * MS);
        assert_eq!(envelope.decide(vel(0.3, 0.0), 100 * MS).cause.as_ref().map(Cause::kind), Some("stop-zone"));
        // Turned away (facing +y), it is beside the robot: free to go.
        envelope.pose(&[1.0, 1.0, std::f64::consts::FRAC_PI_2], 200 * MS);
        envelope.ranges(&scan_ahead(4.0), 200 * MS);
        assert_eq!(envelope.decide(vel(0.3, 0.0), 200 * MS).action, Action::Passed);
        // Forgotten after MEMORY_NS.
        envelope.pose(&[1.0, 1.0, 0.0], MEMORY_NS + 300 * MS);
        envelope.ranges(&scan_ahead(4.0), MEMORY_NS + 300 * MS);
        assert_eq!(envelope.decide(vel(0.3, 0.0), MEMORY_NS + 300 * MS).action, Action::Passed);
    }

    #[test]
    fn late_cycles_widen_the_zones_by_the_distance_covered_meanwhile() {
        // (longest recent interval between judgments ms, ray ahead m,
        // command, expected action, cause kind). Radius 0.2: the clearance
        // is the reading - 0.2; the margin is 0.3 m/s times the interval.
        #[rustfmt::skip]
        let table: Vec<(u64, f64, f64, Action, Option<&str>)> = vec![
            // clearance 0.35: passes with a prompt loop (cap 0.42, ttc 1.17 s) ...
            (50,  0.55, 0.3, Action::Passed,  None),
            // ... slows when 300 ms can pass before the next judgment (0.09 m)
            (300, 0.55, 0.3, Action::Scaled,  Some("time-to-collision")),
            // clearance 0.15: outside the stop zone, unless the robot covers
            // more than 5 cm before it can react
            (50,  0.35, 0.3, Action::Scaled,  Some("slowdown-zone")),
            (300, 0.35, 0.3, Action::Stopped, Some("stop-zone")),
            // a longer stall is budgeted as MAX_REACTION_S at most: clearance
            // 0.3 less 0.15 leaves room to creep (0.9 s would leave 0.03 m)
            (900, 0.50, 0.3, Action::Scaled,  Some("slowdown-zone")),
        ];
        for (interval_ms, ahead, v, action, cause) in table {
            let mut envelope = Envelope::new(settings());
            // Judgments every `interval_ms`, the robot standing still.
            let mut now = 1_000 * MS;
            envelope.ranges(&scan_ahead(4.0), now);
            envelope.decide(ControlCommand::Stop, now);
            now += interval_ms * MS;
            envelope.ranges(&scan_ahead(ahead), now);
            let verdict = envelope.decide(vel(v, 0.0), now);
            assert_eq!(verdict.action, action, "{interval_ms} ms, {ahead} m: {verdict:?}");
            assert_eq!(verdict.cause.as_ref().map(Cause::kind), cause, "{interval_ms} ms, {ahead} m: {verdict:?}");
        }

        // A late cycle is remembered for REACTION_WINDOW_NS, then forgotten
        // once the loop has kept time again.
        let mut envelope = Envelope::new(settings());
        let mut now = 1_000 * MS;
        envelope.decide(ControlCommand::Stop, now);
        now += 300 * MS;
        envelope.decide(ControlCommand::Stop, now);
        assert!(close(envelope.reaction_s(), 0.3));
        while now < 1_300 * MS + REACTION_WINDOW_NS + 100 * MS {
            now += 50 * MS;
            envelope.decide(ControlCommand::Stop, now);
        }
        assert!(close(envelope.reaction_s(), 0.05), "{}", envelope.reaction_s());

        // The scan's age counts too: the robot kept moving at its last
        // speed since the scan was taken.
        let mut envelope = Envelope::new(settings());
        let mut now = 1_000 * MS;
        envelope.ranges(&scan_ahead(4.0), now);
        for _ in 0..3 {
            envelope.decide(vel(0.3, 0.0), now);
            now += 10 * MS;
        }
        envelope.ranges(&scan_ahead(0.35), now);
        assert_eq!(envelope.decide(vel(0.3, 0.0), now).action, Action::Scaled);
        let mut aged = envelope.clone();
        // The same reading, 200 ms old at 0.3 m/s: 6 cm already covered.
        let verdict = aged.decide(vel(0.3, 0.0), now + 200 * MS);
        assert_eq!(verdict.cause.as_ref().map(Cause::kind), Some("stop-zone"), "{verdict:?}");
    }

    #[test]
    fn a_review_only_ever_slows_down() {
        let mut s = settings();
        s.max_accel = 1000.0;
        let mut envelope = Envelope::new(s);
        envelope.ranges(&scan_ahead(4.0), 0);
        envelope.decide(vel(0.0, 0.0), 0);
        let out = envelope.decide(vel(0.3, 0.0), 10 * MS);
        assert_eq!(out.action, Action::Passed);
        assert_eq!(envelope.review(vel(0.3, 0.0), 20 * MS), None, "nothing changed");
        // An obstacle appears in the stop zone: the review stops at once.
        envelope.ranges(&scan_ahead(0.25), 30 * MS);
        let review = envelope.review(vel(0.3, 0.0), 30 * MS).map(|v| v.command);
        assert_eq!(review, Some(ControlCommand::Stop));
        // It goes away: a review does not restart motion; the next command does.
        envelope.ranges(&scan_ahead(4.0), 40 * MS);
        assert_eq!(envelope.review(vel(0.3, 0.0), 40 * MS), None);
        assert_eq!(envelope.decide(vel(0.3, 0.0), 50 * MS).command, vel(0.3, 0.0));
        // GOTO never reaches the motors.
        assert_eq!(envelope.decide(ControlCommand::Goto { x: 1.0, y: 1.0 }, 60 * MS).command, ControlCommand::Stop);
    }
}

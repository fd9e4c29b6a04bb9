//! The queue's decisions, pure and with explicit time (ms since the Unix
//! epoch), so every rule is a table test: which experiment starts next,
//! when each queued one is expected to start (its ETA), whether a user is
//! over a limit and when it frees, and whether a reservation may be booked.
//!
//! The rules, in the order they apply:
//! 1. one experiment runs at a time; a paused queue starts none;
//! 2. inside a reservation only its holder's experiments start, the first
//!    of theirs (in submission order) that ends before the window does;
//! 3. outside reservations the head of the queue starts (first in, first
//!    out), unless it would still run when another user's reservation
//!    begins: then everything waits for that window, so it starts on time;
//! 4. a user has at most `max_queued` experiments waiting (checked, in
//!    preflight or queued) and at most `robot_minutes_per_day` minutes of
//!    robot time in any 24 hours (what ran, runs or waits to run);
//! 5. reservations never overlap, each lasts at most `max_reservation`,
//!    and a user books at most `reservation_per_day` per UTC day;
//! 6. on a lab server ([`place`]): first in, first out, each queued
//!    experiment goes to the first free robot its target names whose
//!    `max-duration` allows it; when no online robot of its target allows
//!    it, to the first free one of its target, which refuses it with its
//!    reason rather than leave it waiting for ever; a robot takes one
//!    experiment at a time;
//! 7. with the owner's duty cycle ([`after_run`]), the robot rests once it
//!    has run its experiments for `run_s`, before the next starts.

pub use crate::store::experiments::{DutyCycle, Limits, Reservation, Target};

/// One day, ms: the window of the robot-minutes limit.
pub const DAY_MS: u64 = 24 * 3600 * 1000;

/// How far ahead an ETA is worked out (experiments past it show none): a
/// queue of long experiments behind many reservations must not make every
/// status request simulate for long.
pub const MAX_ETA_STEPS: usize = 10_000;

/// A queued experiment as the queue sees it.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Waiting {
    pub id: u64,
    pub user: String,
    pub duration_ms: u64,
}

/// What the queue knows at one instant.
#[derive(Clone, Debug, Default)]
pub struct QueueView<'a> {
    pub now_ms: u64,
    /// The running experiment's expected end, if one runs.
    pub running_until_ms: Option<u64>,
    /// Queued experiments, in submission order.
    pub waiting: &'a [Waiting],
    pub reservations: &'a [Reservation],
    pub paused: bool,
    /// Time between one experiment's end and the next one's start (the
    /// reset and two activations), for ETAs.
    pub turnaround_ms: u64,
}

/// The reservation in effect at `at_ms`, if any.
pub fn reservation_at(reservations: &[Reservation], at_ms: u64) -> Option<&Reservation> {
    reservations.iter().find(|r| r.contains(at_ms))
}

/// Which queued experiment may start at `at_ms` (rules 1-3), ignoring
/// what runs: `None` when none may.
fn pick<'w>(waiting: &'w [Waiting], reservations: &[Reservation], at_ms: u64) -> Option<&'w Waiting> {
    if let Some(window) = reservation_at(reservations, at_ms) {
        return waiting.iter().find(|w| w.user == window.user && at_ms.saturating_add(w.duration_ms) <= window.end_ms);
    }
    let head = waiting.first()?;
    let end = at_ms.saturating_add(head.duration_ms);
    let blocked = reservations.iter().any(|r| r.user != head.user && r.start_ms >= at_ms && r.start_ms < end);
    (!blocked).then_some(head)
}

/// The experiment to start now, if any (rules 1-3).
pub fn next_to_start(view: &QueueView<'_>) -> Option<u64> {
    if view.paused || view.running_until_ms.is_some() {
        return None;
    }
    pick(view.waiting, view.reservations, view.now_ms).map(|w| w.id)
}

/// The expected start of every queued experiment (ms), in queue order:
/// `None` for those past [`MAX_ETA_STEPS`] or while the queue is paused.
pub fn etas(view: &QueueView<'_>) -> Vec<(u64, Option<u64>)> {
    let mut etas: Vec<(u64, Option<u64>)> = view.waiting.iter().map(|w| (w.id, None)).collect();
    if view.paused {
        return etas;
    }
    let mut left: Vec<Waiting> = view.waiting.to_vec();
    let mut at = match view.running_until_ms {
        Some(end) => end.max(view.now_ms).saturating_add(view.turnaround_ms),
        None => view.now_ms,
    };
    for _ in 0..MAX_ETA_STEPS {
        if left.is_empty() {
            break;
        }
        match pick(&left, view.reservations, at) {
            Some(chosen) => {
                let (id, duration) = (chosen.id, chosen.duration_ms);
                if let Some(slot) = etas.iter_mut().find(|(e, _)| *e == id) {
                    slot.1 = Some(at);
                }
                left.retain(|w| w.id != id);
                at = at.saturating_add(duration).saturating_add(view.turnaround_ms);
            }
            // Nothing may start now: jump to the next window's start or end.
            None => {
                let next = view.reservations.iter().flat_map(|r| [r.start_ms, r.end_ms]).filter(|t| *t > at).min();
                match next {
                    Some(t) => at = t,
                    None => break,
                }
            }
        }
    }
    etas
}

/// One of a user's experiments as the limits count it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Charge {
    pub submitted_ms: u64,
    /// Waiting to run (checked, in preflight or queued).
    pub waiting: bool,
    /// Robot time it holds: its duration while it waits or runs, what it
    /// ran once it ended, 0 when it never ran.
    pub robot_ms: u64,
}

/// Why a submission is over a limit, and when the limit frees (ms; `None`
/// when only the user can free it, e.g. by cancelling).
#[derive(Clone, Debug, PartialEq)]
pub enum OverLimit {
    Queued { limit: u32, frees_ms: Option<u64> },
    RobotMinutes { limit: f64, used: f64, asked: f64, frees_ms: Option<u64> },
}

impl OverLimit {
    pub fn frees_ms(&self) -> Option<u64> {
        match self {
            OverLimit::Queued { frees_ms, .. } | OverLimit::RobotMinutes { frees_ms, .. } => *frees_ms,
        }
    }
}

/// Whether a user with `charges` may submit one more experiment of
/// `duration_ms` at `now_ms` (rule 4). `first_start_ms`: when the user's
/// first waiting experiment is expected to start (its ETA), which is when
/// the queued limit frees.
pub fn admit(
    limits: &Limits,
    charges: &[Charge],
    duration_ms: u64,
    now_ms: u64,
    first_start_ms: Option<u64>,
) -> Result<(), OverLimit> {
    let waiting = charges.iter().filter(|c| c.waiting).count();
    if waiting as u64 >= u64::from(limits.max_queued) {
        return Err(OverLimit::Queued { limit: limits.max_queued, frees_ms: first_start_ms });
    }
    let budget_ms = (limits.robot_minutes_per_day * 60_000.0).max(0.0) as u64;
    let mut counted: Vec<&Charge> =
        charges.iter().filter(|c| c.submitted_ms.saturating_add(DAY_MS) > now_ms && c.robot_ms > 0).collect();
    let used_ms: u64 = counted.iter().map(|c| c.robot_ms).sum();
    if used_ms.saturating_add(duration_ms) <= budget_ms {
        return Ok(());
    }
    // It frees when enough of the oldest counted ones leave the window.
    counted.sort_by_key(|c| c.submitted_ms);
    let mut left = used_ms;
    let mut frees_ms = None;
    if duration_ms <= budget_ms {
        for charge in counted {
            left -= charge.robot_ms;
            if left.saturating_add(duration_ms) <= budget_ms {
                frees_ms = Some(charge.submitted_ms.saturating_add(DAY_MS));
                break;
            }
        }
    }
    Err(OverLimit::RobotMinutes {
        limit: limits.robot_minutes_per_day,
        used: used_ms as f64 / 60_000.0,
        asked: duration_ms as f64 / 60_000.0,
        frees_ms,
    })
}

/// Why a reservation cannot be booked.
#[derive(Clone, Debug, PartialEq)]
pub enum BookingError {
    /// The window is empty, backwards, or starts in the past.
    Shape(String),
    /// Longer than the owner allows.
    TooLong { limit_s: u64 },
    /// It overlaps another reservation.
    Overlaps(Reservation),
    /// The user's reservations that UTC day would exceed the owner's limit.
    OverDay { limit_s: u64, booked_s: u64 },
}

/// Whether `user` may book `[start_ms, end_ms)` at `now_ms` (rule 5).
pub fn check_booking(
    limits: &Limits,
    reservations: &[Reservation],
    user: &str,
    start_ms: u64,
    end_ms: u64,
    now_ms: u64,
) -> Result<(), BookingError> {
    if end_ms <= start_ms {
        return Err(BookingError::Shape("the window must end after it starts".into()));
    }
    if end_ms <= now_ms {
        return Err(BookingError::Shape("the window is over already".into()));
    }
    let length_s = (end_ms - start_ms) / 1000;
    if end_ms - start_ms > limits.max_reservation_s.saturating_mul(1000) {
        return Err(BookingError::TooLong { limit_s: limits.max_reservation_s });
    }
    if let Some(other) = reservations.iter().find(|r| r.overlaps(start_ms, end_ms)) {
        return Err(BookingError::Overlaps(other.clone()));
    }
    let day = start_ms / DAY_MS;
    let booked_s: u64 = reservations
        .iter()
        .filter(|r| r.user == user && r.start_ms / DAY_MS == day)
        .map(|r| (r.end_ms - r.start_ms) / 1000)
        .sum();
    if booked_s + length_s > limits.reservation_per_day_s {
        return Err(BookingError::OverDay { limit_s: limits.reservation_per_day_s, booked_s });
    }
    Ok(())
}

/// A lab server's robot as the placement sees it.
#[derive(Clone, Debug, PartialEq)]
pub struct Seat {
    pub name: String,
    /// Its profile's id.
    pub profile: String,
    pub max_duration_s: f64,
    /// It may take an experiment now: online, idle, running nothing of the
    /// lab's and being sent nothing.
    pub free: bool,
}

impl Seat {
    fn targeted_by(&self, target: &Target) -> bool {
        match target {
            Target::Any => true,
            Target::Robot(robot) => *robot == self.name,
            Target::Profile(id) => *id == self.profile,
        }
    }

    fn fits(&self, target: &Target, duration_s: f64) -> bool {
        self.targeted_by(target) && duration_s <= self.max_duration_s
    }
}

/// A queued experiment no robot has yet.
#[derive(Clone, Debug, PartialEq)]
pub struct Unplaced {
    pub id: u64,
    pub target: Target,
    pub duration_s: f64,
}

/// Which robot each queued experiment goes to now (rule 6): `(experiment,
/// robot)` pairs. `queued` in submission order, `online` every robot with
/// a live token, by name.
pub fn place(queued: &[Unplaced], online: &[Seat]) -> Vec<(u64, String)> {
    let mut taken: Vec<&str> = Vec::new();
    let mut placed = Vec::new();
    for experiment in queued {
        let anyone_allows = online.iter().any(|seat| seat.fits(&experiment.target, experiment.duration_s));
        let free = online.iter().find(|seat| {
            seat.free
                && !taken.contains(&seat.name.as_str())
                && seat.targeted_by(&experiment.target)
                && (seat.fits(&experiment.target, experiment.duration_s) || !anyone_allows)
        });
        if let Some(seat) = free {
            taken.push(&seat.name);
            placed.push((experiment.id, seat.name.clone()));
        }
    }
    placed
}

/// A lab server's robot as its ETAs see it: its seat, and when it is
/// next free to start one (ms since the Unix epoch): now when idle, its
/// experiment's end when it runs one. A robot out of service (lost,
/// stopped, in maintenance) is not one.
#[derive(Clone, Debug, PartialEq)]
pub struct Freeing {
    pub seat: Seat,
    pub free_at_ms: u64,
}

/// The expected start of every queued experiment of a lab server (ms), in
/// queue order (rule 6 over time): each goes to the robot of its target
/// that frees first (the first by name when two free alike), whose
/// `max-duration` allows it (any of its target when none does), and that
/// robot is then busy for its duration and a turnaround. `None` while the
/// queue is paused or held, for one no robot of its target is in service
/// for, and past [`MAX_ETA_STEPS`].
pub fn fleet_etas(
    queued: &[Unplaced],
    robots: &[Freeing],
    now_ms: u64,
    turnaround_ms: u64,
    paused: bool,
) -> Vec<(u64, Option<u64>)> {
    let mut free_at: Vec<u64> = robots.iter().map(|r| r.free_at_ms.max(now_ms)).collect();
    queued
        .iter()
        .enumerate()
        .map(|(n, experiment)| {
            if paused || n >= MAX_ETA_STEPS {
                return (experiment.id, None);
            }
            let anyone_allows = robots.iter().any(|r| r.seat.fits(&experiment.target, experiment.duration_s));
            let first = robots
                .iter()
                .zip(&free_at)
                .enumerate()
                .filter(|(_, (r, _))| {
                    r.seat.targeted_by(&experiment.target)
                        && (r.seat.fits(&experiment.target, experiment.duration_s) || !anyone_allows)
                })
                .min_by_key(|(_, (r, at))| (**at, r.seat.name.clone()))
                .map(|(i, (_, at))| (i, *at));
            let Some((i, at)) = first else { return (experiment.id, None) };
            let duration_ms = (experiment.duration_s.max(0.0) * 1000.0) as u64;
            free_at[i] = at.saturating_add(duration_ms).saturating_add(turnaround_ms);
            (experiment.id, Some(at))
        })
        .collect()
}

/// When a queued experiment that has not started is refused (ms since
/// the Unix epoch): `queued_at_ms` plus twice the wait its first ETA said
/// (`first_wait_ms`; none while the queue was held), and at least
/// `min_wait_ms`.
pub fn stuck_at(queued_at_ms: u64, first_wait_ms: Option<u64>, min_wait_ms: u64) -> u64 {
    queued_at_ms.saturating_add(first_wait_ms.unwrap_or(0).saturating_mul(2).max(min_wait_ms))
}

/// The duty cycle after a run of `ran_ms`: the robot time counted since
/// the last rest, and until when the robot rests (ms since the Unix
/// epoch), if it now must.
pub fn after_run(duty: Option<DutyCycle>, counted_ms: u64, ran_ms: u64, now_ms: u64) -> (u64, Option<u64>) {
    let Some(duty) = duty else { return (0, None) };
    let counted = counted_ms.saturating_add(ran_ms);
    if counted >= duty.run_s.saturating_mul(1000) {
        (0, Some(now_ms.saturating_add(duty.rest_s.saturating_mul(1000))))
    } else {
        (counted, None)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const S: u64 = 1000;
    const MIN: u64 = 60 * S;

    fn w(id: u64, user: &str, duration_s: u64) -> Waiting {
        Waiting { id, user: user.into(), duration_ms: duration_s * S }
    }

    fn r(id: u64, user: &str, start_s: u64, end_s: u64) -> Reservation {
        Reservation { id, user: user.into(), start_ms: start_s * S, end_ms: end_s * S }
    }

    fn view<'a>(now_s: u64, waiting: &'a [Waiting], reservations: &'a [Reservation]) -> QueueView<'a> {
        QueueView { now_ms: now_s * S, running_until_ms: None, waiting, reservations, paused: false, turnaround_ms: S }
    }

    /// Which experiment starts, as a table: (case, now s, waiting,
    /// reservations, running until s, paused, expected).
    #[test]
    fn the_next_experiment_follows_the_rules_in_order() {
        let queue = [w(1, "ana", 60), w(2, "ben", 30), w(3, "ana", 10)];
        type Case<'a> = (&'a str, u64, &'a [Waiting], Vec<Reservation>, Option<u64>, bool, Option<u64>);
        let cases: Vec<Case<'_>> = vec![
            ("empty queue", 0, &[], vec![], None, false, None),
            ("first in, first out", 0, &queue, vec![], None, false, Some(1)),
            ("one at a time", 0, &queue, vec![], Some(50), false, None),
            ("paused", 0, &queue, vec![], None, true, None),
            ("inside ben's window only ben's run", 100, &queue, vec![r(9, "ben", 90, 200)], None, false, Some(2)),
            ("inside ana's window, her first that fits", 100, &queue, vec![r(9, "ana", 90, 150)], None, false, Some(3)),
            ("inside a window of someone with none queued", 100, &queue, vec![r(9, "cy", 90, 200)], None, false, None),
            ("head would overrun ben's window: wait", 0, &queue, vec![r(9, "ben", 30, 60)], None, false, None),
            ("head ends as ben's window starts", 0, &queue, vec![r(9, "ben", 60, 90)], None, false, Some(1)),
            ("head runs into its own user's window", 0, &queue, vec![r(9, "ana", 30, 90)], None, false, Some(1)),
            ("a window over already changes nothing", 100, &queue, vec![r(9, "ben", 10, 90)], None, false, Some(1)),
        ];
        for (case, now_s, waiting, reservations, running, paused, expected) in cases {
            let mut v = view(now_s, waiting, &reservations);
            v.running_until_ms = running.map(|s| s * S);
            v.paused = paused;
            assert_eq!(next_to_start(&v), expected, "{case}");
        }
    }

    #[test]
    fn etas_add_the_durations_ahead_and_skip_other_users_windows() {
        let queue = [w(1, "ana", 60), w(2, "ben", 30), w(3, "ana", 10)];
        let mut v = view(0, &queue, &[]);
        v.running_until_ms = Some(20 * S);
        // 20 s left of the running one, then 1 s between experiments.
        assert_eq!(etas(&v), vec![(1, Some(21 * S)), (2, Some(82 * S)), (3, Some(113 * S))]);
        // Cy's window at 50..200 s: ana's 60 s cannot start before it ends,
        // and cy has nothing queued, so nothing runs inside it.
        let windows = [r(9, "cy", 50, 200)];
        let v = view(0, &queue, &windows);
        assert_eq!(etas(&v), vec![(1, Some(200 * S)), (2, Some(261 * S)), (3, Some(292 * S))]);
        // Ben's window at 10..100 s: ben's experiment runs inside it, ana's
        // wait for it to end, in order.
        let windows = [r(9, "ben", 10, 100)];
        let v = view(0, &queue, &windows);
        assert_eq!(etas(&v), vec![(1, Some(100 * S)), (2, Some(10 * S)), (3, Some(161 * S))]);
        let mut paused = view(0, &queue, &[]);
        paused.paused = true;
        assert_eq!(etas(&paused), vec![(1, None), (2, None), (3, None)]);
    }

    #[test]
    fn a_long_experiment_waits_for_a_gap_it_fits() {
        let queue = [w(1, "ana", 100)];
        let windows = [r(9, "ben", 50, 100), r(10, "ben", 150, 200)];
        // It fits after 200 s.
        assert_eq!(etas(&view(0, &queue, &windows)), vec![(1, Some(200 * S))]);
        let windows = [r(9, "ben", 50, 100)];
        assert_eq!(etas(&view(0, &queue, &windows)), vec![(1, Some(100 * S))]);
    }

    fn charge(submitted_s: u64, waiting: bool, robot_s: u64) -> Charge {
        Charge { submitted_ms: submitted_s * S, waiting, robot_ms: robot_s * S }
    }

    #[test]
    fn the_queued_limit_counts_waiting_experiments_only() {
        let limits = Limits { max_queued: 2, ..Limits::default() };
        let two_waiting = [charge(0, true, 60), charge(1, true, 60), charge(2, false, 60)];
        assert_eq!(
            admit(&limits, &two_waiting, 60 * S, 10 * S, Some(500 * S)),
            Err(OverLimit::Queued { limit: 2, frees_ms: Some(500 * S) })
        );
        assert_eq!(admit(&limits, &two_waiting[1..], 60 * S, 10 * S, None), Ok(()));
    }

    #[test]
    fn robot_minutes_count_the_last_24_hours_and_say_when_they_free() {
        let limits = Limits { robot_minutes_per_day: 5.0, max_queued: 100, ..Limits::default() };
        let day = DAY_MS / S;
        // 2 min at t=0, 2 min at t=1000 s, a refused one (0 robot time).
        let charges = [charge(0, false, 120), charge(1000, false, 120), charge(2000, false, 0)];
        assert_eq!(admit(&limits, &charges, MIN, 3000 * S, None), Ok(()));
        let over = admit(&limits, &charges, 2 * MIN, 3000 * S, None);
        // 4 used + 2 asked > 5: the first leaves the window at 24 h.
        assert_eq!(over, Err(OverLimit::RobotMinutes { limit: 5.0, used: 4.0, asked: 2.0, frees_ms: Some(DAY_MS) }));
        // After a day the first no longer counts.
        assert_eq!(admit(&limits, &charges, 2 * MIN, (day + 1) * S, None), Ok(()));
        // More than the whole budget never frees.
        let never = admit(&limits, &[], 6 * MIN, 0, None);
        assert!(matches!(never, Err(OverLimit::RobotMinutes { frees_ms: None, .. })), "{never:?}");
    }

    #[test]
    fn bookings_are_bounded_and_never_overlap() {
        let limits = Limits { max_reservation_s: 1800, reservation_per_day_s: 3600, ..Limits::default() };
        let booked = [r(1, "ana", 1000, 2000), r(2, "ana", 3000, 4000)];
        type Case<'a> = (&'a str, &'a str, u64, u64, Result<(), BookingError>);
        let cases: Vec<Case<'_>> = vec![
            ("fine", "ben", 5000, 6800, Ok(())),
            ("backwards", "ben", 6000, 5000, Err(BookingError::Shape("the window must end after it starts".into()))),
            ("over already", "ben", 10, 20, Err(BookingError::Shape("the window is over already".into()))),
            ("too long", "ben", 5000, 6801, Err(BookingError::TooLong { limit_s: 1800 })),
            ("overlaps", "ben", 1500, 2500, Err(BookingError::Overlaps(r(1, "ana", 1000, 2000)))),
            ("touching is fine", "ben", 2000, 3000, Ok(())),
            ("ana's day is full", "ana", 5000, 6700, Err(BookingError::OverDay { limit_s: 3600, booked_s: 2000 })),
            ("ana's next day is free", "ana", DAY_MS / S + 10, DAY_MS / S + 1000, Ok(())),
        ];
        for (case, user, start_s, end_s, expected) in cases {
            assert_eq!(check_booking(&limits, &booked, user, start_s * S, end_s * S, 100 * S), expected, "{case}");
        }
    }

    fn seat(name: &str, profile: &str, max_duration_s: f64, free: bool) -> super::Seat {
        super::Seat { name: name.into(), profile: profile.into(), max_duration_s, free }
    }

    fn unplaced(id: u64, target: super::Target, duration_s: f64) -> super::Unplaced {
        super::Unplaced { id, target, duration_s }
    }

    /// A lab server's ETAs: each queued experiment starts when the first
    /// robot of its target that allows it frees, and keeps it busy for its
    /// duration and the turnaround.
    #[test]
    fn a_lab_servers_etas_follow_each_robots_end_and_the_targets() {
        use super::Target::{Any, Profile, Robot};
        let at = |name: &str, profile: &str, max_s: f64, free_s: u64| super::Freeing {
            seat: seat(name, profile, max_s, free_s == 0),
            free_at_ms: free_s * S,
        };
        // r1 (profile pa, up to 60 s) runs until 100 s; r2 (pa, 600 s) is
        // idle; r3 (pb, 600 s) runs until 40 s. Turnaround 10 s, now 0.
        let fleet = [at("r1", "pa", 60.0, 100), at("r2", "pa", 600.0, 0), at("r3", "pb", 600.0, 40)];
        type Case<'a> = (&'a str, Vec<super::Unplaced>, &'a [super::Freeing], bool, Vec<Option<u64>>);
        let cases: Vec<Case<'_>> = vec![
            ("one, to the idle robot", vec![unplaced(1, Any, 30.0)], &fleet, false, vec![Some(0)]),
            (
                "three: r2 now, r3 at its end, then r2 again",
                vec![unplaced(1, Any, 30.0), unplaced(2, Any, 30.0), unplaced(3, Any, 30.0)],
                &fleet,
                false,
                vec![Some(0), Some(40 * S), Some(40 * S)],
            ),
            (
                "a 300 s one skips r1 (60 s at most), waits for r2",
                vec![unplaced(1, Profile("pa".into()), 300.0), unplaced(2, Profile("pa".into()), 300.0)],
                &fleet,
                false,
                vec![Some(0), Some(310 * S)],
            ),
            (
                "one for r1 waits for r1's end",
                vec![unplaced(1, Robot("r1".into()), 30.0), unplaced(2, Robot("r1".into()), 30.0)],
                &fleet,
                false,
                vec![Some(100 * S), Some(140 * S)],
            ),
            (
                "none of its target allows it: the first of its target that frees (it refuses it)",
                vec![unplaced(1, Robot("r1".into()), 900.0)],
                &fleet,
                false,
                vec![Some(100 * S)],
            ),
            ("no such robot in service", vec![unplaced(1, Robot("r9".into()), 30.0)], &fleet, false, vec![None]),
            ("no robot at all", vec![unplaced(1, Any, 30.0)], &[], false, vec![None]),
            ("paused or held", vec![unplaced(1, Any, 30.0), unplaced(2, Any, 5.0)], &fleet, true, vec![None, None]),
        ];
        for (case, queued, robots, paused, expected) in cases {
            let etas = super::fleet_etas(&queued, robots, 0, 10 * S, paused);
            let ids: Vec<u64> = queued.iter().map(|q| q.id).collect();
            assert_eq!(etas, ids.into_iter().zip(expected).collect::<Vec<_>>(), "{case}");
        }
        // A robot whose end is past: free now, not in the past.
        let late = [at("r1", "pa", 60.0, 5)];
        assert_eq!(super::fleet_etas(&[unplaced(1, Any, 30.0)], &late, 50 * S, 0, false), vec![(1, Some(50 * S))]);
    }

    #[test]
    fn each_queued_experiment_goes_to_the_first_free_robot_that_fits() {
        use super::Target::{Any, Profile, Robot};
        let fleet = || vec![seat("r1", "pa", 60.0, true), seat("r2", "pa", 600.0, true), seat("r3", "pb", 600.0, true)];
        let busy = |name: &str| {
            let mut seats = fleet();
            seats.iter_mut().filter(|s| s.name == name).for_each(|s| s.free = false);
            seats
        };
        type Case = (&'static str, Vec<super::Unplaced>, Vec<super::Seat>, Vec<(u64, &'static str)>);
        let cases: Vec<Case> = vec![
            ("nothing queued", vec![], fleet(), vec![]),
            ("no robot online", vec![unplaced(1, Any, 30.0)], vec![], vec![]),
            (
                "first in, first free",
                vec![unplaced(1, Any, 30.0), unplaced(2, Any, 30.0)],
                fleet(),
                vec![(1, "r1"), (2, "r2")],
            ),
            (
                "one each, the rest wait",
                (1..=4).map(|i| unplaced(i, Any, 30.0)).collect(),
                fleet(),
                vec![(1, "r1"), (2, "r2"), (3, "r3")],
            ),
            ("a busy robot is passed", vec![unplaced(1, Any, 30.0)], busy("r1"), vec![(1, "r2")]),
            ("a named robot only", vec![unplaced(1, Robot("r3".into()), 30.0)], fleet(), vec![(1, "r3")]),
            ("a named robot that is busy: it waits", vec![unplaced(1, Robot("r3".into()), 30.0)], busy("r3"), vec![]),
            ("a profile", vec![unplaced(1, Profile("pb".into()), 30.0)], fleet(), vec![(1, "r3")]),
            ("too long for r1: the next that allows it", vec![unplaced(1, Any, 120.0)], fleet(), vec![(1, "r2")]),
            (
                "the one that allows it is busy: it waits",
                vec![unplaced(1, Profile("pa".into()), 120.0)],
                busy("r2"),
                vec![],
            ),
            (
                "no robot of its target allows it: the first free one refuses it",
                vec![unplaced(1, Profile("pa".into()), 900.0)],
                fleet(),
                vec![(1, "r1")],
            ),
            (
                "the head waits, the next goes",
                vec![unplaced(1, Robot("r1".into()), 30.0), unplaced(2, Any, 30.0)],
                busy("r1"),
                vec![(2, "r2")],
            ),
            ("an unknown robot: it waits", vec![unplaced(1, Robot("r9".into()), 30.0)], fleet(), vec![]),
        ];
        for (case, queued, online, expected) in cases {
            let expected: Vec<(u64, String)> = expected.into_iter().map(|(id, r)| (id, r.to_string())).collect();
            assert_eq!(super::place(&queued, &online), expected, "{case}");
        }
    }

    #[test]
    fn a_queued_experiment_is_stuck_after_twice_its_first_eta_and_at_least_the_minimum() {
        let min = 15 * 60_000;
        for (queued, first_wait, want) in [
            (1_000, None, 1_000 + min),
            (1_000, Some(60_000), 1_000 + min),
            (1_000, Some(10 * 60_000), 1_000 + 20 * 60_000),
            (u64::MAX - 5, Some(u64::MAX), u64::MAX),
        ] {
            assert_eq!(stuck_at(queued, first_wait, min), want, "{queued} {first_wait:?}");
        }
    }

    #[test]
    fn the_duty_cycle_rests_the_robot_once_its_run_time_is_used() {
        let duty = Some(DutyCycle { run_s: 60, rest_s: 30 });
        for (duty, counted, ran, want) in [
            (None, 0, 3_600_000, (0, None)),
            (duty, 0, 20_000, (20_000, None)),
            (duty, 40_000, 19_999, (59_999, None)),
            (duty, 40_000, 20_000, (0, Some(1_000 + 30_000))),
            (duty, 0, 90_000, (0, Some(1_000 + 30_000))),
        ] {
            assert_eq!(after_run(duty, counted, ran, 1_000), want, "{duty:?} {counted} {ran}");
        }
    }
}

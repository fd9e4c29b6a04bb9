//! Reservations: a window of robot time booked by a researcher (for
//! themselves) or an admin (for anyone). Inside it only the holder's
//! experiments start and the holder may drive. The rules are pure in
//! [`super::queue`]; here they are applied under the lab's lock and
//! audited.

use super::queue;
use super::{Lab, LabError, MAX_BOOKING_AHEAD};
use crate::deploy::utc_time;
use crate::runtime::locks::unix_now_ms;
use crate::store::experiments::{MAX_RESERVATIONS, Reservation};
use crate::store::users::{Principal, Role};

impl Lab {
    /// Books `[start_ms, end_ms)` for `user` (researchers for themselves,
    /// admins for anyone).
    pub fn book(&self, user: &Principal, for_user: &str, start_ms: u64, end_ms: u64) -> Result<Reservation, LabError> {
        let target = format!("reservation for {for_user}");
        let booked = || {
            if !user.may_submit() {
                return Err(LabError::Forbidden(format!("{} may not book the robot", user.name)));
            }
            if for_user != user.name && user.role != Role::Admin {
                return Err(LabError::Forbidden(format!("{} may book only for themselves", user.name)));
            }
            if self.fleet().is_some() {
                return Err(LabError::Conflict(
                    "reservations are for one robot: book on that robot's own portal".into(),
                ));
            }
            let mut book = self.lock()?;
            let now = unix_now_ms();
            check_times(start_ms, end_ms, now)?;
            if start_ms > now.saturating_add(MAX_BOOKING_AHEAD.as_millis() as u64) {
                return Err(LabError::BadRequest(format!(
                    "a reservation starts at most {} days ahead",
                    MAX_BOOKING_AHEAD.as_secs() / 86_400
                )));
            }
            let start_ms = start_ms.max(now);
            queue::check_booking(&book.lab.settings.limits, &book.lab.reservations, for_user, start_ms, end_ms, now)
                .map_err(|e| booking_error(e, for_user))?;
            let mut lab = book.lab.clone();
            if lab.reservations.len() >= MAX_RESERVATIONS {
                lab.reservations.retain(|r| r.end_ms > now);
            }
            if lab.reservations.len() >= MAX_RESERVATIONS {
                return Err(LabError::Conflict(format!("the lab holds {MAX_RESERVATIONS} reservations already")));
            }
            let reservation = Reservation { id: lab.next_reservation, user: for_user.to_string(), start_ms, end_ms };
            lab.next_reservation += 1;
            lab.reservations.push(reservation.clone());
            lab.reservations.sort_by_key(|r| r.start_ms);
            self.store().lock()?.put_lab_state(&lab)?;
            book.lab = lab;
            drop(book);
            self.notify();
            Ok(reservation)
        };
        self.audited(&user.name, "book", &target, booked, |r| {
            format!("reservation {} from {} to {}", r.id, utc_time(r.start_ms), utc_time(r.end_ms))
        })
    }

    /// Cancels reservation `id` (its holder, or an admin: the owner).
    pub fn unbook(&self, user: &Principal, id: u64) -> Result<(), LabError> {
        let target = format!("reservation {id}");
        let unbooked = || {
            let mut book = self.lock()?;
            let found = book.lab.reservations.iter().find(|r| r.id == id);
            if !found.is_some_and(|r| user.role == Role::Admin || r.user == user.name) {
                return Err(LabError::NotFound(format!("no reservation {id}")));
            }
            let mut lab = book.lab.clone();
            lab.reservations.retain(|r| r.id != id);
            self.store().lock()?.put_lab_state(&lab)?;
            book.lab = lab;
            drop(book);
            self.notify();
            Ok(())
        };
        self.audited(&user.name, "unbook", &target, unbooked, |()| "cancelled".to_string())
    }

    /// Whether `user` holds the reservation in effect now (a researcher
    /// may drive inside it).
    pub fn holds_reservation_now(&self, user: &str) -> bool {
        self.book
            .lock()
            .ok()
            .and_then(|b| queue::reservation_at(&b.lab.reservations, unix_now_ms()).map(|r| r.user == user))
            .unwrap_or(false)
    }
}

/// Earliest time a request may name, ms since the Unix epoch (2001-09-09):
/// anything smaller is seconds given where milliseconds were meant.
const EARLIEST_MS: u64 = 1_000_000_000_000;

/// What a window's times say before any rule of the queue: milliseconds,
/// and not over already (a window in the past would otherwise be clamped
/// to start now and read as ending before it starts).
fn check_times(start_ms: u64, end_ms: u64, now_ms: u64) -> Result<(), LabError> {
    for (field, at) in [("start_unix_ms", start_ms), ("end_unix_ms", end_ms)] {
        if at < EARLIEST_MS {
            return Err(LabError::BadRequest(format!(
                "{field} {at} looks like seconds: times are milliseconds since the Unix epoch ({at}000?)"
            )));
        }
    }
    if end_ms <= now_ms {
        return Err(LabError::BadRequest(format!(
            "the window ends at {}, which is past already; the host's clock says {}",
            utc_time(end_ms),
            utc_time(now_ms)
        )));
    }
    Ok(())
}

fn booking_error(e: queue::BookingError, user: &str) -> LabError {
    use queue::BookingError;
    match e {
        BookingError::Shape(why) => LabError::BadRequest(format!("the reservation: {why}")),
        BookingError::TooLong { limit_s } => {
            LabError::BadRequest(format!("a reservation lasts at most {} min", limit_s / 60))
        }
        BookingError::Overlaps(other) => LabError::Conflict(format!(
            "it overlaps reservation {} ({} to {})",
            other.id,
            utc_time(other.start_ms),
            utc_time(other.end_ms)
        )),
        BookingError::OverDay { limit_s, booked_s } => LabError::OverLimit {
            message: format!("{user} has {} min booked that day; at most {} min a day", booked_s / 60, limit_s / 60),
            retry_after_s: None,
        },
    }
}

#[cfg(test)]
mod tests {
    use super::check_times;

    #[test]
    fn a_windows_times_are_milliseconds_and_not_past() {
        let now = 1_795_874_709_000;
        // (start, end, the error's words; None: accepted)
        let cases = [
            (now + 60_000, now + 120_000, None),
            (now - 60_000, now + 60_000, None),
            (1_795_874_769, 1_795_874_829, Some("start_unix_ms 1795874769 looks like seconds")),
            (now + 1, 1_795_874_829, Some("end_unix_ms 1795874829 looks like seconds")),
            (now - 120_000, now - 60_000, Some("which is past already")),
        ];
        for (start, end, words) in cases {
            match (check_times(start, end, now), words) {
                (Ok(()), None) => {}
                (Err(e), Some(words)) => assert!(e.to_string().contains(words), "{e}"),
                (got, _) => panic!("{start}..{end}: {got:?}"),
            }
        }
    }
}

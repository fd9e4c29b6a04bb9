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

//! The wall clock: the one place the host reads the time since the Unix
//! epoch ([`unix_now_ns`] and the coarser readings built on it), and the
//! one way a time of day is shown to a person ([`shown`]): `HH:MM:SS UTC`
//! today, with its date on any other day, so a reservation a week ahead
//! never reads as this morning. Dates come from `jiff`, not a copied
//! calendar rule.
//!
//! Durations on the robot are never measured here: the graph's clock
//! (`runtime::control_loop::Clock`, simulated or real) does that.

use std::time::{SystemTime, UNIX_EPOCH};

/// Nanoseconds since the Unix epoch, now (0 if the clock is before it).
pub fn unix_now_ns() -> u64 {
    SystemTime::now().duration_since(UNIX_EPOCH).map_or(0, |d| d.as_nanos() as u64)
}

/// Milliseconds since the Unix epoch, now.
pub fn unix_now_ms() -> u64 {
    unix_now_ns() / 1_000_000
}

/// Seconds since the Unix epoch, now.
pub fn unix_now_s() -> u64 {
    unix_now_ns() / 1_000_000_000
}

/// Seconds since the Unix epoch, now, with their fraction (log lines).
pub fn unix_now_s_f64() -> f64 {
    unix_now_ns() as f64 / 1e9
}

/// `unix_ms` as a person reads it, now: see [`shown_at`].
pub fn shown(unix_ms: u64) -> String {
    shown_at(unix_ms, unix_now_ms())
}

/// `unix_ms` as a person reads it at `now_ms`: `HH:MM:SS UTC` on the same
/// UTC day, `YYYY-MM-DD HH:MM:SS UTC` on any other.
pub fn shown_at(unix_ms: u64, now_ms: u64) -> String {
    let (Some(at), Some(now)) = (timestamp(unix_ms), timestamp(now_ms)) else {
        return format!("{unix_ms} ms after the Unix epoch");
    };
    let same_day = at.to_zoned(jiff::tz::TimeZone::UTC).date() == now.to_zoned(jiff::tz::TimeZone::UTC).date();
    if same_day { at.strftime("%H:%M:%S UTC").to_string() } else { at.strftime("%Y-%m-%d %H:%M:%S UTC").to_string() }
}

/// `YYYYMMDD-HHMMSS` in UTC (file names: they sort by time).
pub fn stamp(unix_s: u64) -> String {
    match timestamp(unix_s.saturating_mul(1000)) {
        Some(at) => at.strftime("%Y%m%d-%H%M%S").to_string(),
        None => format!("{unix_s}"),
    }
}

fn timestamp(unix_ms: u64) -> Option<jiff::Timestamp> {
    jiff::Timestamp::from_millisecond(i64::try_from(unix_ms).ok()?).ok()
}

#[cfg(test)]
mod tests {
    use super::{shown_at, stamp};

    #[test]
    fn times_carry_their_date_when_not_today() {
        // 2026-11-28 14:05:09 UTC.
        let now = 1_795_874_709_000;
        let cases = [
            (now, "14:05:09 UTC"),
            (now - 14 * 3600 * 1000, "00:05:09 UTC"),
            (now - 15 * 3600 * 1000, "2026-11-27 23:05:09 UTC"),
            (now + 10 * 3600 * 1000, "2026-11-29 00:05:09 UTC"),
            (now + 30 * 86_400 * 1000, "2026-12-28 14:05:09 UTC"),
            (0, "1970-01-01 00:00:00 UTC"),
        ];
        for (at, expected) in cases {
            assert_eq!(shown_at(at, now), expected, "{at}");
        }
    }

    #[test]
    fn stamps_are_utc_calendar_dates() {
        let cases = [(0, "19700101-000000"), (951_782_400, "20000229-000000"), (1_795_874_709, "20261128-140509")];
        for (unix_s, expected) in cases {
            assert_eq!(stamp(unix_s), expected);
        }
    }
}

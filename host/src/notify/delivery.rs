//! The delivery thread: every destination (a webhook's URL, or
//! `mailto:ADDRESS`) gets its waiting events in the order they were
//! written, one at a time, each until its receiver acknowledges it (or it
//! has been tried [`MAX_ATTEMPTS`] times), with backoff between tries. A
//! destination that fails waits on its own: the others go on. Holds no
//! lock while it talks.

use std::collections::BTreeMap;
use std::time::{Duration, Instant};

use super::mail::MAILTO;
use super::outbox::Entry;
use super::{Notifier, NotifyError};
use crate::walltime::unix_now_s;

/// The first retry's wait; each next one waits twice as long.
pub const FIRST_RETRY: Duration = Duration::from_millis(250);
/// The longest wait between two tries: a receiver back up is reached soon.
pub const LONGEST_RETRY: Duration = Duration::from_secs(300);
/// Tries of one event before it is given up (logged): a receiver gone for
/// good must not hold the events behind it forever (about 3 hours).
pub const MAX_ATTEMPTS: u32 = 40;
/// The longest sleep with nothing due: a clock that jumped is caught up.
const IDLE_WAIT: Duration = Duration::from_secs(60);

/// The wait before try `attempt` (1 is the first retry).
pub fn backoff(attempt: u32) -> Duration {
    let factor = 1u32.checked_shl(attempt.saturating_sub(1)).unwrap_or(u32::MAX);
    FIRST_RETRY.saturating_mul(factor).min(LONGEST_RETRY)
}

/// One destination's failures since its last delivery.
#[derive(Clone, Copy, Debug)]
struct Failing {
    attempts: u32,
    next_try: Instant,
}

/// Which of `waiting` (each destination's oldest event) are due at `now`,
/// and how long until the next one is when none is.
fn due(waiting: &[Entry], failing: &BTreeMap<String, Failing>, now: Instant) -> (Vec<Entry>, Duration) {
    let mut ready = Vec::new();
    let mut sleep = IDLE_WAIT;
    for entry in waiting {
        match failing.get(&entry.hook) {
            Some(f) if f.next_try > now => sleep = sleep.min(f.next_try - now),
            _ => ready.push(entry.clone()),
        }
    }
    (ready, sleep)
}

/// Runs forever on the delivery thread.
pub(crate) fn deliver_forever(notifier: &Notifier) {
    let mut failing: BTreeMap<String, Failing> = BTreeMap::new();
    let mut dropped_told = 0u64;
    loop {
        let (waiting, dropped, last_id) = match notifier.outbox() {
            Ok(outbox) => (outbox.oldest_per_destination(), outbox.dropped(), outbox.last_id()),
            Err(e) => {
                tracing::error!("notifications: delivery stops: {e}");
                return;
            }
        };
        if dropped > dropped_told {
            tracing::warn!("notifications: {dropped} events dropped so far because the outbox was full");
            dropped_told = dropped;
        }
        failing.retain(|hook, _| waiting.iter().any(|e| &e.hook == hook));
        let (ready, sleep) = due(&waiting, &failing, Instant::now());
        if ready.is_empty() {
            notifier.wait_for_news(last_id, sleep);
            continue;
        }
        for entry in ready {
            let id = entry.event.id;
            match deliver(notifier, &entry) {
                Ok(()) => {
                    failing.remove(&entry.hook);
                    forget(notifier, id);
                }
                Err(e) => {
                    let attempts = failing.get(&entry.hook).map_or(0, |f| f.attempts) + 1;
                    if attempts >= MAX_ATTEMPTS {
                        tracing::error!("notifications: event {id} given up after {attempts} tries: {e}");
                        failing.remove(&entry.hook);
                        forget(notifier, id);
                    } else {
                        let wait = backoff(attempts);
                        tracing::warn!(
                            "notifications: event {id} not delivered (try {attempts}), again in {wait:?}: {e}"
                        );
                        failing.insert(entry.hook.clone(), Failing { attempts, next_try: Instant::now() + wait });
                    }
                }
            }
        }
    }
}

fn deliver(notifier: &Notifier, entry: &Entry) -> Result<(), NotifyError> {
    if let Some(address) = entry.hook.strip_prefix(MAILTO) {
        let Some(mailer) = notifier.mailer() else {
            return Err(NotifyError::Gone(entry.hook.clone()));
        };
        return Ok(mailer.send(address, &entry.event)?);
    }
    let Some(hook) = notifier.hook(&entry.hook) else {
        return Err(NotifyError::Gone(entry.hook.clone()));
    };
    let body = serde_json::to_vec(&entry.event).map_err(|e| NotifyError::Gone(format!("{}: {e}", entry.hook)))?;
    Ok(super::webhook::post(&hook.agent, &hook.url, &hook.secret, entry.event.id, unix_now_s(), &body)?)
}

fn forget(notifier: &Notifier, id: u64) {
    match notifier.outbox().and_then(|mut outbox| outbox.remove(id)) {
        Ok(()) => {}
        Err(e) => tracing::error!("notifications: event {id} sent but cannot be removed from the outbox: {e}"),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::notify::{Event, EventKind};

    #[test]
    fn retries_wait_twice_as_long_each_time_up_to_the_longest() {
        assert_eq!(backoff(1), FIRST_RETRY);
        assert_eq!(backoff(2), FIRST_RETRY * 2);
        assert_eq!(backoff(5), FIRST_RETRY * 16);
        assert_eq!(backoff(30), LONGEST_RETRY);
        assert_eq!(backoff(u32::MAX), LONGEST_RETRY);
    }

    fn entry(hook: &str, id: u64) -> Entry {
        Entry {
            hook: hook.into(),
            event: Event { id, event: EventKind::ExperimentEnded, at_ms: 0, experiment: None, robot: None },
        }
    }

    #[test]
    fn a_failing_destination_waits_alone_and_the_others_go_on() {
        let now = Instant::now();
        let waiting = [entry("http://down/", 1), entry("mailto:a@b", 2), entry("http://up/", 3)];
        let mut failing = BTreeMap::new();
        failing.insert("http://down/".to_string(), Failing { attempts: 3, next_try: now + Duration::from_secs(2) });
        let (ready, sleep) = due(&waiting, &failing, now);
        let ids: Vec<u64> = ready.iter().map(|e| e.event.id).collect();
        assert_eq!(ids, [2, 3], "the failing hook's event waits; the others are due");
        assert_eq!(sleep, Duration::from_secs(2));
        let (ready, sleep) = due(&waiting[..1], &failing, now);
        assert!(ready.is_empty());
        assert_eq!(sleep, Duration::from_secs(2), "nothing due: sleep until the failing one's next try");
        let (ready, _) = due(&waiting[..1], &failing, now + Duration::from_secs(2));
        assert_eq!(ready.len(), 1, "due again at its next try");
    }
}

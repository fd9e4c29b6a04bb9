//! The cameras' latest frames for the portal's live view
//! (`GET /api/v1/cameras/{name}/live`, docs/camera.md "Live"): a host
//! service ([`LiveCameras`]) holding, for each running camera, a
//! `tokio::sync::watch` of its newest frame. The camera's thread offers each
//! frame it queues; only while someone watches is the frame copied (one
//! `Arc` shared by every watcher), so a camera nobody watches costs nothing
//! here. The watch keeps only the newest frame: a slow watcher skips
//! frames, never holds the camera or the loop.

use std::collections::BTreeMap;
use std::sync::{Arc, Mutex, PoisonError, Weak};

use tokio::sync::watch;

use super::Frame;

/// The newest frame of a camera, once there is one.
pub type Latest = Option<Arc<Frame>>;

/// Every running camera's feed, by component name: the feeds of cameras
/// of that name, oldest first (while a new set is built beside the running
/// one, both have one; the newest is watched, and when it goes, because
/// its set did not start, the one before is watched again). Held weakly:
/// a camera's feed ends with the camera.
#[derive(Debug, Default)]
pub struct LiveCameras {
    feeds: Mutex<BTreeMap<String, Vec<Weak<watch::Sender<Latest>>>>>,
}

impl LiveCameras {
    /// A feed for camera `name`, watched instead of the one of a camera of
    /// that name in the set before (whose watchers' streams end with it).
    pub fn publish(self: &Arc<Self>, name: &str) -> LiveFeed {
        let sender = Arc::new(watch::Sender::new(None));
        let mut feeds = self.feeds.lock().unwrap_or_else(PoisonError::into_inner);
        feeds.entry(name.to_string()).or_default().push(Arc::downgrade(&sender));
        LiveFeed { name: name.to_string(), sender, cameras: self.clone() }
    }

    /// The newest frames of camera `name`, if it runs.
    pub fn watch(&self, name: &str) -> Option<watch::Receiver<Latest>> {
        let feeds = self.feeds.lock().unwrap_or_else(PoisonError::into_inner);
        feeds.get(name)?.iter().rev().find_map(Weak::upgrade).map(|sender| sender.subscribe())
    }

    /// The running cameras' names.
    pub fn names(&self) -> Vec<String> {
        let feeds = self.feeds.lock().unwrap_or_else(PoisonError::into_inner);
        feeds
            .iter()
            .filter(|(_, senders)| senders.iter().any(|s| s.strong_count() > 0))
            .map(|(n, _)| n.clone())
            .collect()
    }
}

/// One camera's side of its feed; dropping it (the camera stops) ends its
/// watchers' streams.
#[derive(Debug)]
pub struct LiveFeed {
    name: String,
    sender: Arc<watch::Sender<Latest>>,
    cameras: Arc<LiveCameras>,
}

impl LiveFeed {
    /// Offers `frame` to the watchers, if any.
    pub fn offer(&self, frame: &Frame) {
        if self.sender.receiver_count() > 0 {
            self.sender.send_replace(Some(Arc::new(frame.clone())));
        }
    }
}

impl Drop for LiveFeed {
    fn drop(&mut self) {
        let mut feeds = self.cameras.feeds.lock().unwrap_or_else(PoisonError::into_inner);
        if let Some(senders) = feeds.get_mut(&self.name) {
            let mine = Arc::downgrade(&self.sender);
            senders.retain(|sender| !sender.ptr_eq(&mine) && sender.strong_count() > 0);
            if senders.is_empty() {
                feeds.remove(&self.name);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]

    use super::*;

    fn frame(seq: u64) -> Frame {
        Frame { jpeg: vec![0xff, 0xd8, 0xff, 0xd9], width: 1, height: 1, capture_ns: seq, frame_ns: seq, seq }
    }

    #[test]
    fn watchers_see_the_newest_frame_and_the_end_of_the_camera() {
        let cameras = Arc::new(LiveCameras::default());
        let feed = cameras.publish("overhead");
        feed.offer(&frame(0)); // nobody watches: not kept
        let mut watcher = cameras.watch("overhead").unwrap();
        assert!(watcher.borrow().is_none());
        feed.offer(&frame(1));
        feed.offer(&frame(2));
        assert!(watcher.has_changed().unwrap());
        assert_eq!(watcher.borrow_and_update().as_ref().unwrap().seq, 2);
        assert_eq!(cameras.names(), vec!["overhead".to_string()]);
        // The next set's camera of the same name is watched; the old one's
        // end does not remove it.
        let next = cameras.publish("overhead");
        let mut on_next = cameras.watch("overhead").unwrap();
        next.offer(&frame(7));
        assert_eq!(on_next.borrow_and_update().as_ref().unwrap().seq, 7);
        drop(feed);
        assert!(watcher.has_changed().is_err(), "the old camera's watchers end");
        assert!(cameras.watch("overhead").is_some());
        drop(next);
        assert!(cameras.watch("overhead").is_none());
        assert!(cameras.names().is_empty());
        // A set that did not start: its camera goes, the running one is
        // watched again.
        let running = cameras.publish("overhead");
        let failed = cameras.publish("overhead");
        drop(failed);
        let mut again = cameras.watch("overhead").unwrap();
        running.offer(&frame(9));
        assert_eq!(again.borrow_and_update().as_ref().unwrap().seq, 9);
    }
}

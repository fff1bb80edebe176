//! Counted admission: holds counted per key (a principal's sessions and uploads, a client's
//! unary registrations), each released when it drops, and a session's [`Admission`] (a server
//! slot and its principal's quota). The one place such a count goes down, whether the hold ends
//! normally or its admission fails half-way. Below the session registry ([`crate::live`]), the
//! compute engine and the shared state, which all hold these.

use std::collections::HashMap;
use std::sync::{Arc, Mutex};
use tokio::sync::OwnedSemaphorePermit;

/// Holds counted per key, each released when it drops.
#[derive(Default)]
pub struct PerKey {
    counts: Mutex<HashMap<String, usize>>,
}

/// One unit of a [`PerKey`] count; uncounted on drop.
pub struct KeyHold {
    key: String,
    of: Arc<PerKey>,
}

impl PerKey {
    /// One more hold of `key` if it holds fewer than `limit`; else how many it holds.
    pub fn try_hold(self: &Arc<Self>, key: &str, limit: usize) -> Result<KeyHold, usize> {
        let mut m = self.counts.lock().unwrap_or_else(|e| e.into_inner());
        let n = m.entry(key.to_string()).or_insert(0);
        if *n >= limit {
            let held = *n;
            if held == 0 {
                m.remove(key);
            }
            return Err(held);
        }
        *n += 1;
        Ok(KeyHold {
            key: key.to_string(),
            of: self.clone(),
        })
    }

    /// How many holds `key` has now.
    pub fn held(&self, key: &str) -> usize {
        let m = self.counts.lock().unwrap_or_else(|e| e.into_inner());
        m.get(key).copied().unwrap_or(0)
    }
}

impl Drop for KeyHold {
    fn drop(&mut self) {
        let mut m = self.of.counts.lock().unwrap_or_else(|e| e.into_inner());
        if let Some(n) = m.get_mut(&self.key) {
            *n -= 1;
            if *n == 0 {
                m.remove(&self.key);
            }
        }
    }
}

/// A session's hold on a server slot and, when it has one, on its principal's quota; both
/// released when it drops.
pub struct Admission {
    _permit: OwnedSemaphorePermit,
    _quota: Option<KeyHold>,
}

impl Admission {
    /// The hold of `permit` (a server slot) and `quota`.
    pub fn new(permit: OwnedSemaphorePermit, quota: Option<KeyHold>) -> Self {
        Self {
            _permit: permit,
            _quota: quota,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A key counts its holds up to its limit, goes down as each drops (the map forgets a key
    /// at zero), and an admission gives back its slot and its quota together.
    #[test]
    fn holds_count_up_to_the_limit_and_down_on_drop() {
        let per = Arc::new(PerKey::default());
        let a = per.try_hold("alice", 2).unwrap();
        let b = per.try_hold("alice", 2).unwrap();
        assert_eq!(per.try_hold("alice", 2).err(), Some(2));
        assert_eq!(per.held("bob"), 0);
        let c = per.try_hold("bob", 1).unwrap();
        drop(a);
        assert_eq!(per.held("alice"), 1);
        let a2 = per.try_hold("alice", 2).unwrap();
        drop((a2, b, c));
        assert_eq!((per.held("alice"), per.held("bob")), (0, 0));
        assert!(per.counts.lock().unwrap().is_empty());
        assert_eq!(per.try_hold("carol", 0).err(), Some(0));
        assert!(per.counts.lock().unwrap().is_empty());

        let slots = Arc::new(tokio::sync::Semaphore::new(1));
        let admission = Admission::new(
            slots.clone().try_acquire_owned().unwrap(),
            Some(per.try_hold("alice", 1).unwrap()),
        );
        assert_eq!((slots.available_permits(), per.held("alice")), (0, 1));
        drop(admission);
        assert_eq!((slots.available_permits(), per.held("alice")), (1, 0));
    }
}

//! Which stream holds each streamed session: one session id has one live stream.
//!
//! A resume of a session (`SessionStart.resume_session_id`) takes it over: the newest stream
//! holds the session, and the stream that held it before ends with ABORTED (error reason
//! [`TAKEN_OVER`]) the next time it wakes — it sends no further answer and records nothing more.
//! The two never record interleaved: every record a stream writes for its session goes through
//! its [`Lease`], which writes only while the stream still holds the session, under the session's
//! gate; a resume reads the recorded messages and writes its takeover under the same gate. So the
//! resumed session is rebuilt from exactly what the previous holder recorded (and answered), and
//! no `client_seq` is ever recorded, or answered, twice with different content.
//!
//! The server's session slot (and the principal's quota) passes from the old stream to the new
//! one: a resume of a session that is live here needs no new slot.

use crate::counted::Admission;
use std::collections::HashMap;
use std::sync::{Arc, Mutex};
use tokio::sync::watch;

pub use crate::error::TAKEN_OVER;

/// What the stream holding a session holds.
struct Holder {
    /// The holding stream's number (each takeover adds one).
    generation: u64,
    /// The server slot and quota the session holds (dropped: released).
    admission: Option<Admission>,
    /// The holding stream is running (its lease not dropped).
    alive: bool,
    /// A resume holds the gate: a holder that ends leaves its slot for it to take.
    taking: bool,
}

/// One session's place in [`Live`].
pub struct Slot {
    /// Serialises the session's records and a resume's read of them.
    gate: Arc<tokio::sync::Mutex<()>>,
    holder: Mutex<Holder>,
    /// The holding stream's generation, for the streams that wait.
    changed: watch::Sender<u64>,
}

impl Slot {
    fn holder(&self) -> std::sync::MutexGuard<'_, Holder> {
        self.holder.lock().unwrap_or_else(|e| e.into_inner())
    }
}

/// The live sessions of this server (by session id).
#[derive(Default)]
pub struct Live {
    map: Mutex<HashMap<String, Arc<Slot>>>,
}

/// A stream's hold on its session. Dropped by the holding stream: the session's slot is released
/// and it is no longer live; dropped by a stream that was taken over: nothing (the new holder
/// has the slot).
pub struct Lease {
    live: Arc<Live>,
    sid: String,
    slot: Arc<Slot>,
    generation: u64,
    rx: watch::Receiver<u64>,
}

/// A resume's exclusive hold on a session while it reads the record and takes it over.
pub struct Takeover {
    live: Arc<Live>,
    sid: String,
    slot: Arc<Slot>,
    gate: Option<tokio::sync::OwnedMutexGuard<()>>,
    taken: bool,
}

/// The session was taken over by a newer stream.
#[derive(Debug, Clone, Copy)]
pub struct TakenOver;

impl Live {
    fn map(&self) -> std::sync::MutexGuard<'_, HashMap<String, Arc<Slot>>> {
        self.map.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// A new session `sid` (a fresh id) held by the calling stream with `admission`.
    pub fn start(self: &Arc<Self>, sid: &str, admission: Admission) -> Lease {
        let (changed, rx) = watch::channel(1);
        let slot = Arc::new(Slot {
            gate: Default::default(),
            holder: Mutex::new(Holder {
                generation: 1,
                admission: Some(admission),
                alive: true,
                taking: false,
            }),
            changed,
        });
        self.map().insert(sid.to_string(), slot.clone());
        Lease {
            live: self.clone(),
            sid: sid.to_string(),
            slot,
            generation: 1,
            rx,
        }
    }

    /// Whether a stream holds session `sid` now.
    pub fn is_live(&self, sid: &str) -> bool {
        self.map().get(sid).is_some_and(|s| s.holder().alive)
    }

    /// The session `sid`'s slot, made when it is not live here.
    fn slot(&self, sid: &str) -> Arc<Slot> {
        self.map()
            .entry(sid.to_string())
            .or_insert_with(|| {
                let (changed, _) = watch::channel(0);
                Arc::new(Slot {
                    gate: Default::default(),
                    holder: Mutex::new(Holder {
                        generation: 0,
                        admission: None,
                        alive: false,
                        taking: false,
                    }),
                    changed,
                })
            })
            .clone()
    }

    /// Removes `slot` as `sid`'s slot when it is the one there, no stream holds it and no
    /// resume holds or awaits its gate (that resume finds it still in place).
    fn forget(&self, sid: &str, slot: &Arc<Slot>) {
        let mut m = self.map();
        if m.get(sid).is_some_and(|s| Arc::ptr_eq(s, slot))
            && slot.holder().admission.is_none()
            && slot.gate.try_lock().is_ok()
        {
            m.remove(sid);
        }
    }

    /// Waits for exclusive hold of session `sid`: its records cannot change until the
    /// [`Takeover`] is dropped or turned into a [`Lease`].
    pub async fn lock(self: &Arc<Self>, sid: &str) -> Takeover {
        loop {
            let slot = self.slot(sid);
            let gate = slot.gate.clone().lock_owned().await;
            // The slot may have been forgotten before its gate was taken (its stream ended and
            // nobody held the gate then): take the current one. Once the gate is held and the
            // slot is current, it stays so (`forget` needs the gate free).
            if self.map().get(sid).is_some_and(|s| Arc::ptr_eq(s, &slot)) {
                slot.holder().taking = true;
                return Takeover {
                    live: self.clone(),
                    sid: sid.to_string(),
                    slot,
                    gate: Some(gate),
                    taken: false,
                };
            }
        }
    }
}

impl Takeover {
    /// Whether the session holds a slot now (a stream holds it, or held it when this resume
    /// took the gate): its slot and quota pass to the new holder, which needs none of its own.
    pub fn held(&self) -> bool {
        self.slot.holder().admission.is_some()
    }

    /// The calling stream holds the session from now: the previous holder (if any) is told,
    /// and its slot and quota pass on; `admission` is used when there was none.
    pub fn take(mut self, admission: Option<Admission>) -> Lease {
        let (generation, spare) = {
            let mut h = self.slot.holder();
            h.generation += 1;
            h.alive = true;
            h.taking = false;
            let spare = match h.admission {
                None => {
                    h.admission = admission;
                    None
                }
                Some(_) => admission,
            };
            (h.generation, spare)
        };
        // A slot taken for nothing is released (outside the holder's lock).
        drop(spare);
        self.taken = true;
        self.slot.changed.send_replace(generation);
        // The gate opens once the new holder is in place.
        self.gate = None;
        Lease {
            live: self.live.clone(),
            sid: self.sid.clone(),
            slot: self.slot.clone(),
            generation,
            rx: self.slot.changed.subscribe(),
        }
    }
}

impl Drop for Takeover {
    fn drop(&mut self) {
        // A resume that did not take the session: a slot its holder left meanwhile is released,
        // and no slot of the map is left behind.
        let released = if self.taken {
            None
        } else {
            let mut h = self.slot.holder();
            h.taking = false;
            if h.alive { None } else { h.admission.take() }
        };
        drop(released);
        self.gate = None;
        self.live.forget(&self.sid, &self.slot);
    }
}

impl Lease {
    /// Whether this stream still holds its session.
    pub fn holds(&self) -> bool {
        self.slot.holder().generation == self.generation
    }

    /// Runs `write` (the session's records) only while this stream holds the session, and so
    /// that a resume cannot read the record in between.
    pub async fn record<F, T, E>(&self, write: F) -> Result<Result<T, E>, TakenOver>
    where
        F: std::future::Future<Output = Result<T, E>>,
    {
        let _gate = self.slot.gate.lock().await;
        if !self.holds() {
            return Err(TakenOver);
        }
        Ok(write.await)
    }

    /// Resolves when a newer stream takes the session over.
    pub async fn taken_over(&mut self) {
        let mine = self.generation;
        if self.rx.wait_for(|g| *g != mine).await.is_err() {
            // The sender is gone (it cannot be: the lease keeps its slot): never.
            std::future::pending::<()>().await;
        }
    }
}

impl Drop for Lease {
    fn drop(&mut self) {
        let released = {
            let mut h = self.slot.holder();
            if h.generation == self.generation {
                h.alive = false;
                // A resume waiting at the gate takes the slot over (or releases it).
                if h.taking { None } else { h.admission.take() }
            } else {
                None
            }
        };
        // Released outside the holder's lock.
        drop(released);
        self.live.forget(&self.sid, &self.slot);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::atomic::Ordering;

    /// Server slots, counted as they are held.
    #[derive(Clone)]
    struct Slots(Arc<tokio::sync::Semaphore>);
    const SLOTS: usize = 64;
    impl Slots {
        fn new() -> Self {
            Self(Arc::new(tokio::sync::Semaphore::new(SLOTS)))
        }
        /// How many are held.
        fn load(&self, _: Ordering) -> usize {
            SLOTS - self.0.available_permits()
        }
    }
    fn admission(n: &Slots) -> Admission {
        Admission::new(n.0.clone().try_acquire_owned().unwrap(), None)
    }

    #[tokio::test]
    async fn a_resume_takes_over_the_slot_and_fences_the_old_stream() {
        let live = Arc::new(Live::default());
        let slots = Slots::new();
        let mut old = live.start("s1-1", admission(&slots));
        assert!(old.holds() && live.is_live("s1-1"));
        assert_eq!(old.record(async { Ok::<_, ()>(7) }).await.unwrap(), Ok(7));
        let t = live.lock("s1-1").await;
        assert!(t.held());
        // While the resume reads, the old stream cannot record.
        let blocked = tokio::time::timeout(
            std::time::Duration::from_millis(50),
            old.record(async { Ok::<_, ()>(()) }),
        )
        .await;
        assert!(
            blocked.is_err(),
            "the old stream recorded during a takeover"
        );
        let new = t.take(None);
        // The slot passed on: still one.
        assert_eq!(slots.load(Ordering::SeqCst), 1);
        assert!(!old.holds() && new.holds());
        tokio::time::timeout(std::time::Duration::from_secs(1), old.taken_over())
            .await
            .expect("the old stream is told");
        assert!(old.record(async { Ok::<_, ()>(()) }).await.is_err());
        drop(old);
        assert_eq!(
            slots.load(Ordering::SeqCst),
            1,
            "the old stream released the new one's slot"
        );
        assert!(live.is_live("s1-1"));
        drop(new);
        assert_eq!(slots.load(Ordering::SeqCst), 0);
        assert!(!live.is_live("s1-1"));
    }

    #[tokio::test]
    async fn a_holder_ending_during_a_takeover_leaves_its_slot_to_it() {
        let live = Arc::new(Live::default());
        let slots = Slots::new();
        // Taken: the slot passes on although its holder ended after the resume saw it held.
        let old = live.start("s1-4", admission(&slots));
        let t = live.lock("s1-4").await;
        assert!(t.held());
        drop(old);
        assert_eq!(
            slots.load(Ordering::SeqCst),
            1,
            "the slot was released under the resume"
        );
        let new = t.take(None);
        assert!(new.holds());
        assert_eq!(slots.load(Ordering::SeqCst), 1);
        // Refused: the slot the ended holder left is released with the resume.
        let t = live.lock("s1-4").await;
        drop(new);
        assert_eq!(slots.load(Ordering::SeqCst), 1);
        drop(t);
        assert_eq!(slots.load(Ordering::SeqCst), 0);
        assert!(!live.is_live("s1-4"));
        // Refused while the holder runs: it keeps its slot.
        let old = live.start("s1-4", admission(&slots));
        drop(live.lock("s1-4").await);
        assert!(old.holds() && live.is_live("s1-4"));
        assert_eq!(slots.load(Ordering::SeqCst), 1);
        drop(old);
        assert_eq!(slots.load(Ordering::SeqCst), 0);
    }

    #[tokio::test]
    async fn a_resume_of_an_ended_session_needs_a_slot_and_a_refused_one_leaves_nothing() {
        let live = Arc::new(Live::default());
        let slots = Slots::new();
        let t = live.lock("s1-2").await;
        assert!(!t.held());
        drop(t);
        assert!(!live.is_live("s1-2"));
        let t = live.lock("s1-2").await;
        let l = t.take(Some(admission(&slots)));
        assert_eq!(slots.load(Ordering::SeqCst), 1);
        assert!(l.holds());
        drop(l);
        assert_eq!(slots.load(Ordering::SeqCst), 0);
        assert!(!live.is_live("s1-2"));
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 4)]
    async fn concurrent_resumes_leave_exactly_one_holder() {
        let live = Arc::new(Live::default());
        let slots = Slots::new();
        let first = live.start("s1-3", admission(&slots));
        let mut tasks = Vec::new();
        for _ in 0..16 {
            let live = live.clone();
            let slots = slots.clone();
            tasks.push(tokio::spawn(async move {
                let t = live.lock("s1-3").await;
                let a = (!t.held()).then(|| admission(&slots));
                t.take(a)
            }));
        }
        let mut leases = vec![first];
        for t in tasks {
            leases.push(t.await.unwrap());
        }
        assert_eq!(leases.iter().filter(|l| l.holds()).count(), 1);
        assert_eq!(slots.load(Ordering::SeqCst), 1);
        drop(leases);
        assert_eq!(slots.load(Ordering::SeqCst), 0);
        assert!(!live.is_live("s1-3"));
    }
}

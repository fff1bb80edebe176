//! The cases a server knows: those ready to register against (a snapshot map, replaced on each
//! change so that readers never wait), and the state of every case (LOADING, READY, FAILED),
//! watched by `WatchCase`.

use crate::cases::Case;
use librplus_proto::v1 as pb;
use std::collections::{BTreeMap, BTreeSet};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, RwLock};
use tokio::sync::watch;

/// Ready cases by id.
pub type Ready = Arc<BTreeMap<String, Arc<Case>>>;

/// The registry.
#[derive(Default)]
pub struct Registry {
    ready: RwLock<Ready>,
    states: Mutex<BTreeMap<String, watch::Sender<pb::CaseStatus>>>,
    uploaded: Mutex<BTreeSet<String>>,
    /// Uploaded cases evicted from memory (STORED), until they are READY again.
    evicted: Mutex<BTreeSet<String>>,
    preloaded: AtomicBool,
}

impl Registry {
    /// The ready cases now.
    pub fn ready(&self) -> Ready {
        self.ready.read().unwrap_or_else(|e| e.into_inner()).clone()
    }

    /// Whether the preload at start is done.
    pub fn preloaded(&self) -> bool {
        self.preloaded.load(Ordering::Acquire)
    }

    /// Marks the preload at start done.
    pub fn set_preloaded(&self) {
        self.preloaded.store(true, Ordering::Release);
    }

    /// Sets a case's state (creating its watch); a READY state with its case makes it served.
    pub fn set(&self, status: pb::CaseStatus, case: Option<Arc<Case>>) {
        let id = status.case_id.clone();
        if case.is_some() || status.state == pb::CaseState::Failed as i32 {
            self.evicted
                .lock()
                .unwrap_or_else(|e| e.into_inner())
                .remove(&id);
        }
        if let Some(c) = case {
            let mut r = self.ready.write().unwrap_or_else(|e| e.into_inner());
            let mut m = (**r).clone();
            m.insert(id.clone(), c);
            *r = Arc::new(m);
        }
        let mut s = self.states.lock().unwrap_or_else(|e| e.into_inner());
        match s.get(&id) {
            Some(tx) => {
                tx.send_replace(status);
            }
            None => {
                s.insert(id, watch::channel(status).0);
            }
        }
    }

    /// Marks a case as uploaded over the API since the start (its status then belongs to an
    /// upload, also once a failed upload was removed from the store; not to a case the server
    /// was started with).
    pub fn set_uploaded(&self, id: &str) {
        self.uploaded
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .insert(id.to_string());
    }

    /// Whether a case was uploaded over the API since the start.
    pub fn is_uploaded(&self, id: &str) -> bool {
        self.uploaded
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .contains(id)
    }

    /// A case's state, and a receiver of its changes.
    pub fn watch(&self, id: &str) -> Option<watch::Receiver<pb::CaseStatus>> {
        self.states
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .get(id)
            .map(|tx| tx.subscribe())
    }

    /// A case's state.
    pub fn status(&self, id: &str) -> Option<pb::CaseStatus> {
        self.watch(id).map(|rx| rx.borrow().clone())
    }

    /// Takes ready case `id` out of memory when it is still `case` and no session uses it: its
    /// state becomes STORED (the next request loads it again). Whether it was evicted.
    pub fn evict(&self, id: &str, case: &Arc<Case>) -> bool {
        {
            let mut r = self.ready.write().unwrap_or_else(|e| e.into_inner());
            let current = r.get(id).is_some_and(|c| Arc::ptr_eq(c, case));
            if !current || case.sessions.load(Ordering::SeqCst) > 0 {
                return false;
            }
            let mut m = (**r).clone();
            m.remove(id);
            *r = Arc::new(m);
        }
        self.evicted
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .insert(id.to_string());
        self.set(
            pb::CaseStatus {
                case_id: id.to_string(),
                version: case.version.clone(),
                state: pb::CaseState::Stored as i32,
                stage: String::new(),
                fraction: 0.0,
                error: String::new(),
                seconds: 0.0,
                coarse_basis: false,
            },
            None,
        );
        true
    }

    /// Whether `id` was evicted and is not READY again yet.
    pub fn is_evicted(&self, id: &str) -> bool {
        self.evicted
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .contains(id)
    }

    /// Switches evicted case `id` from STORED to LOADING; true for the one caller that does
    /// (it starts the load), false when it is not STORED.
    pub fn begin_reload(&self, id: &str) -> bool {
        let s = self.states.lock().unwrap_or_else(|e| e.into_inner());
        let Some(tx) = s.get(id) else {
            return false;
        };
        let mut switched = false;
        tx.send_if_modified(|st| {
            if st.state == pb::CaseState::Stored as i32 {
                st.state = pb::CaseState::Loading as i32;
                st.stage = "queued".into();
                switched = true;
            }
            switched
        });
        switched
    }

    /// Serves case `id` no more, keeping its state (a coarse case whose own basis failed: the
    /// FAILED status set next says why).
    pub fn unserve(&self, id: &str) {
        let mut r = self.ready.write().unwrap_or_else(|e| e.into_inner());
        if r.contains_key(id) {
            let mut m = (**r).clone();
            m.remove(id);
            *r = Arc::new(m);
        }
    }

    /// Forgets a case (served no more); its watchers see it FAILED "deleted".
    pub fn remove(&self, id: &str) -> Option<Arc<Case>> {
        let case = {
            let mut r = self.ready.write().unwrap_or_else(|e| e.into_inner());
            let mut m = (**r).clone();
            let c = m.remove(id);
            *r = Arc::new(m);
            c
        };
        self.uploaded
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .remove(id);
        self.evicted
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .remove(id);
        if let Some(tx) = self
            .states
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .remove(id)
        {
            let mut st = tx.borrow().clone();
            st.state = pb::CaseState::Failed as i32;
            st.error = "the case was deleted".into();
            tx.send_replace(st);
        }
        case
    }

    /// Every case's state, by id.
    pub fn all(&self) -> Vec<pb::CaseStatus> {
        self.states
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .values()
            .map(|tx| tx.borrow().clone())
            .collect()
    }
}

/// The status of a ready case.
pub(crate) fn ready_status(c: &Case) -> pb::CaseStatus {
    pb::CaseStatus {
        case_id: c.id.clone(),
        version: c.version.clone(),
        state: pb::CaseState::Ready as i32,
        stage: String::new(),
        fraction: 1.0,
        error: String::new(),
        seconds: c.prepared.seconds,
        coarse_basis: c.coarse.is_some(),
    }
}

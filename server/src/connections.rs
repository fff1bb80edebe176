//! The open client connections and what each has shown of itself: connections that have had
//! no call accepted (authenticated, or any call without an auth file) are bounded per address
//! and in total, and closed when they open no call within `connection_idle_timeout_s`, so that
//! peers without credentials cannot fill `max_connections`; connections of authenticated
//! clients are never closed to make room.

use std::collections::{BTreeMap, HashMap};
use std::net::{IpAddr, SocketAddr};
use std::sync::{Arc, Mutex};
use std::time::Duration;
use tokio::sync::oneshot;

/// Why a connection was closed by the server.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Closed {
    /// It opened no call within `connection_idle_timeout_s`.
    Idle,
    /// Its address held `max_unauthenticated_connections_per_address` connections of no
    /// accepted call, and it was the oldest.
    PerAddress,
    /// Connections of no accepted call held half of `max_connections`, and it was the oldest.
    Unauthenticated,
    /// `max_connections` were open, and it was the oldest of no accepted call.
    Full,
}

impl Closed {
    /// The reason as a metrics label.
    pub fn label(self) -> &'static str {
        match self {
            Closed::Idle => "idle",
            Closed::PerAddress => "per_address",
            Closed::Unauthenticated => "unauthenticated",
            Closed::Full => "full",
        }
    }
}

/// One open connection.
struct Entry {
    /// Its place in the order of admission.
    seq: u64,
    /// A call of it was accepted.
    trusted: bool,
    /// It opened a call (accepted or not).
    used: bool,
    /// Closes it (None once trusted: it is never closed by the table).
    kill: Option<oneshot::Sender<Closed>>,
}

#[derive(Default)]
struct Table {
    open: HashMap<SocketAddr, Entry>,
    /// The connections of no accepted call, oldest first.
    untrusted: BTreeMap<u64, SocketAddr>,
    /// How many of them each address holds.
    per_ip: HashMap<IpAddr, usize>,
    next: u64,
}

impl Table {
    /// Removes `peer` from the untrusted order (it was trusted, closed, or is being evicted).
    fn untrust_remove(&mut self, peer: SocketAddr, seq: u64) {
        if self.untrusted.remove(&seq).is_some()
            && let Some(n) = self.per_ip.get_mut(&peer.ip())
        {
            *n -= 1;
            if *n == 0 {
                self.per_ip.remove(&peer.ip());
            }
        }
    }

    /// Closes the oldest connection of no accepted call (of address `ip` when given).
    fn evict_oldest(&mut self, ip: Option<IpAddr>, why: Closed) -> bool {
        let victim = self
            .untrusted
            .iter()
            .find(|(_, a)| ip.is_none_or(|ip| a.ip() == ip))
            .map(|(&s, &a)| (s, a));
        let Some((seq, peer)) = victim else {
            return false;
        };
        self.untrust_remove(peer, seq);
        if let Some(e) = self.open.remove(&peer)
            && let Some(k) = e.kill
        {
            let _ = k.send(why);
        }
        metrics::counter!("librplus_connections_closed_total", "reason" => why.label())
            .increment(1);
        true
    }
}

/// The open connections ([`Connections::admit`] counts one, [`Connections::called`] marks the
/// one a call was accepted on).
pub struct Connections {
    max: usize,
    max_untrusted: usize,
    per_address: usize,
    idle: Duration,
    table: Mutex<Table>,
}

/// A connection admitted: uncounted when dropped; `closed` fires when the server closes it.
pub struct Admitted {
    peer: SocketAddr,
    seq: u64,
    of: Arc<Connections>,
    /// Fires with the reason when the server closes the connection.
    pub closed: oneshot::Receiver<Closed>,
}

impl Admitted {
    /// The connection's key in the table: its peer address and its place in the order.
    pub fn id(&self) -> (SocketAddr, u64) {
        (self.peer, self.seq)
    }
}

impl Drop for Admitted {
    fn drop(&mut self) {
        let mut t = self.of.lock();
        if t.open.get(&self.peer).is_some_and(|e| e.seq == self.seq) {
            t.open.remove(&self.peer);
        }
        t.untrust_remove(self.peer, self.seq);
    }
}

impl Connections {
    /// The limits of `config`: `max_connections`, half of them of no accepted call,
    /// `max_unauthenticated_connections_per_address`, `connection_idle_timeout_s`.
    pub fn new(config: &crate::config::ServerConfig) -> Self {
        let max = config.max_connections.max(1);
        Self {
            max,
            max_untrusted: (max / 2).max(1),
            per_address: config.max_unauthenticated_connections_per_address.max(1),
            idle: Duration::from_secs_f64(config.connection_idle_timeout_s.clamp(0.001, 1e9)),
            table: Mutex::new(Table::default()),
        }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Table> {
        self.table.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// How long a connection may go without a call ([`Connections::expire`] after it).
    pub fn idle_timeout(&self) -> Duration {
        self.idle
    }

    /// Counts a connection from `peer` that has sent its first bytes, making room by closing
    /// the oldest connection of no accepted call where a limit would be passed; None when
    /// `max_connections` are open and every one of them had a call accepted.
    pub fn admit(self: &Arc<Self>, peer: SocketAddr) -> Option<Admitted> {
        let mut t = self.lock();
        if t.per_ip.get(&peer.ip()).copied().unwrap_or(0) >= self.per_address {
            t.evict_oldest(Some(peer.ip()), Closed::PerAddress);
        }
        if t.untrusted.len() >= self.max_untrusted {
            t.evict_oldest(None, Closed::Unauthenticated);
        }
        if t.open.len() >= self.max && !t.evict_oldest(None, Closed::Full) {
            return None;
        }
        let seq = t.next;
        t.next += 1;
        let (kill, closed) = oneshot::channel();
        if let Some(old) = t.open.insert(
            peer,
            Entry {
                seq,
                trusted: false,
                used: false,
                kill: Some(kill),
            },
        ) {
            // The same address and port again: the old connection is gone.
            t.untrust_remove(peer, old.seq);
        }
        t.untrusted.insert(seq, peer);
        *t.per_ip.entry(peer.ip()).or_insert(0) += 1;
        Some(Admitted {
            peer,
            seq,
            of: self.clone(),
            closed,
        })
    }

    /// A call arrived on the connection of `peer` (`accepted`: its caller was authenticated, or
    /// there is no auth file): it is no longer idle, and an accepted one is never closed to
    /// make room.
    pub fn called(&self, peer: Option<SocketAddr>, accepted: bool) {
        let Some(peer) = peer else {
            return;
        };
        let mut t = self.lock();
        let Some(e) = t.open.get_mut(&peer) else {
            return;
        };
        e.used = true;
        if accepted && !e.trusted {
            e.trusted = true;
            e.kill = None;
            let seq = e.seq;
            t.untrust_remove(peer, seq);
        }
    }

    /// Closes the connection `id` ([`Admitted::id`]) if it opened no call yet: what the
    /// gate does `connection_idle_timeout_s` after admitting it.
    pub fn expire(&self, id: (SocketAddr, u64)) {
        let (peer, seq) = id;
        let mut t = self.lock();
        let idle = t
            .open
            .get(&peer)
            .is_some_and(|e| e.seq == seq && !e.used && !e.trusted);
        if idle {
            t.untrust_remove(peer, seq);
            if let Some(k) = t.open.remove(&peer).and_then(|e| e.kill) {
                let _ = k.send(Closed::Idle);
            }
            metrics::counter!("librplus_connections_closed_total", "reason" => "idle").increment(1);
        }
    }

    /// Open connections, and how many of them had no call accepted.
    pub fn counts(&self) -> (usize, usize) {
        let t = self.lock();
        (t.open.len(), t.untrusted.len())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn table(max: usize, per_address: usize) -> Arc<Connections> {
        Arc::new(Connections::new(&crate::config::ServerConfig {
            max_connections: max,
            max_unauthenticated_connections_per_address: per_address,
            ..Default::default()
        }))
    }

    fn addr(ip: u8, port: u16) -> SocketAddr {
        SocketAddr::from(([127, 0, 0, ip], port))
    }

    #[test]
    fn one_address_holds_at_most_its_share_and_its_oldest_goes_first() {
        let c = table(100, 3);
        let mut a: Vec<Admitted> = (0..3).map(|p| c.admit(addr(2, p)).unwrap()).collect();
        let other = c.admit(addr(3, 1)).unwrap();
        a.push(c.admit(addr(2, 9)).unwrap());
        assert_eq!(a[0].closed.try_recv(), Ok(Closed::PerAddress));
        for x in &mut a[1..] {
            assert!(x.closed.try_recv().is_err());
        }
        let mut other = other;
        assert!(other.closed.try_recv().is_err());
        assert_eq!(c.counts(), (4, 4));
    }

    #[test]
    fn connections_of_no_accepted_call_take_half_and_trusted_ones_are_kept() {
        let c = table(8, 100);
        let mut trusted = Vec::new();
        for p in 0..4 {
            let a = c.admit(addr(1, p)).unwrap();
            c.called(Some(addr(1, p)), true);
            trusted.push(a);
        }
        let mut untrusted: Vec<Admitted> = (0..4).map(|p| c.admit(addr(2, p)).unwrap()).collect();
        assert_eq!(c.counts(), (8, 4));
        // Full: a new one closes the oldest untrusted, never a trusted one.
        let _n = c.admit(addr(2, 50)).unwrap();
        assert_eq!(untrusted[0].closed.try_recv(), Ok(Closed::Unauthenticated));
        for t in &mut trusted {
            assert!(t.closed.try_recv().is_err());
        }
        // Every connection trusted and the table full: the next is refused.
        let mut all = Vec::new();
        for x in untrusted.drain(1..) {
            c.called(Some(x.peer), true);
            all.push(x);
        }
        c.called(Some(addr(2, 50)), true);
        assert_eq!(c.counts(), (8, 0));
        assert!(c.admit(addr(9, 1)).is_none());
        // One closes: room again.
        drop(trusted.pop());
        assert!(c.admit(addr(9, 1)).is_some());
    }

    #[test]
    fn an_idle_connection_expires_and_a_used_one_does_not() {
        let c = table(8, 8);
        let mut idle = c.admit(addr(2, 1)).unwrap();
        let mut used = c.admit(addr(2, 2)).unwrap();
        c.called(Some(addr(2, 2)), false);
        c.expire(idle.id());
        c.expire(used.id());
        assert_eq!(idle.closed.try_recv(), Ok(Closed::Idle));
        assert!(used.closed.try_recv().is_err());
        // A used connection that was never accepted still counts as unauthenticated.
        assert_eq!(c.counts(), (1, 1));
        drop(used);
        assert_eq!(c.counts(), (0, 0));
    }
}

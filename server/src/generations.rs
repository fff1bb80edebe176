//! One listener, successive gRPC servers ("generations") for successive TLS settings, and the
//! gate every connection passes first.

use super::Reload;
use crate::connections::{Admitted, Closed, Connections};
use std::collections::VecDeque;
use std::convert::Infallible;
use std::future::Future;
use std::pin::Pin;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::task::{Context, Poll};
use std::time::Duration;
use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::{mpsc, oneshot};
use tokio_stream::wrappers::ReceiverStream;
use tonic::transport::server::{Connected, Router, TcpConnectInfo};

type Conn = Result<Counted, Infallible>;

/// The connections that have not spoken yet, oldest first: (id, the signal that closes it).
type Silent = VecDeque<(u64, oneshot::Sender<()>)>;

/// Connection admission: each connection must send its first bytes within `preface`; at
/// most `max / 4` may wait silently (a new one closes the oldest silent one, so a flood of
/// silent connections cannot keep a real client out); those that have spoken are counted in
/// the [`Connections`] table, which bounds the ones of no accepted call and closes them
/// when they open no call in time.
pub(super) struct Gate {
    conns: Arc<Connections>,
    max_silent: usize,
    preface: Duration,
    silent: Arc<Mutex<Silent>>,
    next: AtomicU64,
}

impl Gate {
    pub(super) fn new(conns: Arc<Connections>, max: usize, preface: Duration) -> Self {
        Self {
            conns,
            max_silent: (max / 4).max(1),
            preface,
            silent: Default::default(),
            next: AtomicU64::new(0),
        }
    }

    /// Admits an accepted connection: waits (in a task) for its first bytes, counts it,
    /// then hands it to `conns`; or closes it.
    fn admit(&self, s: TcpStream, conns: mpsc::Sender<Conn>) {
        let id = self.next.fetch_add(1, Ordering::Relaxed);
        let (kill, killed) = oneshot::channel::<()>();
        {
            let mut q = self.silent.lock().unwrap_or_else(|e| e.into_inner());
            q.push_back((id, kill));
            while q.len() > self.max_silent {
                if let Some((_, k)) = q.pop_front() {
                    let _ = k.send(());
                }
            }
        }
        let silent = self.silent.clone();
        let preface = self.preface;
        let table = self.conns.clone();
        tokio::spawn(async move {
            // `peek` waits for a byte (readiness alone has false positives); 0: closed.
            let mut byte = [0u8; 1];
            let spoke = tokio::select! {
                r = tokio::time::timeout(preface, s.peek(&mut byte)) => matches!(r, Ok(Ok(n)) if n > 0),
                _ = killed => false,
            };
            silent
                .lock()
                .unwrap_or_else(|e| e.into_inner())
                .retain(|(i, _)| *i != id);
            if !spoke {
                metrics::counter!("librplus_connections_refused_total", "reason" => "silent")
                    .increment(1);
                return;
            }
            let Some(admitted) = s.peer_addr().ok().and_then(|a| table.admit(a)) else {
                metrics::counter!("librplus_connections_refused_total", "reason" => "limit")
                    .increment(1);
                tracing::debug!("connection limit reached; connection closed");
                return;
            };
            let key = admitted.id();
            let expiry = table.clone();
            tokio::spawn(async move {
                tokio::time::sleep(expiry.idle_timeout()).await;
                expiry.expire(key);
            });
            let _ = conns
                .send(Ok(Counted {
                    io: s,
                    admitted,
                    closed: None,
                }))
                .await;
        });
    }
}

/// An admitted connection: counted until it closes, and closed when the table says so.
pub(super) struct Counted {
    io: TcpStream,
    admitted: Admitted,
    /// Why the table closed it, once it did; None while it may.
    closed: Option<Option<Closed>>,
}

impl Counted {
    /// The reason the table closed this connection, once it did.
    fn closed(&mut self, cx: &mut Context<'_>) -> Option<Closed> {
        if self.closed.is_none() {
            match Pin::new(&mut self.admitted.closed).poll(cx) {
                Poll::Ready(Ok(why)) => self.closed = Some(Some(why)),
                // Trusted: never closed by the table.
                Poll::Ready(Err(_)) => self.closed = Some(None),
                Poll::Pending => {}
            }
        }
        self.closed.flatten()
    }
}

impl Connected for Counted {
    type ConnectInfo = TcpConnectInfo;
    fn connect_info(&self) -> TcpConnectInfo {
        self.io.connect_info()
    }
}

impl AsyncRead for Counted {
    fn poll_read(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<std::io::Result<()>> {
        let me = self.get_mut();
        if let Some(why) = me.closed(cx) {
            tracing::debug!(reason = why.label(), "connection closed by the server");
            return Poll::Ready(Err(std::io::Error::new(
                std::io::ErrorKind::ConnectionAborted,
                format!("closed by the server ({})", why.label()),
            )));
        }
        Pin::new(&mut me.io).poll_read(cx, buf)
    }
}

impl AsyncWrite for Counted {
    fn poll_write(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<std::io::Result<usize>> {
        Pin::new(&mut self.get_mut().io).poll_write(cx, buf)
    }
    fn poll_write_vectored(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        bufs: &[std::io::IoSlice<'_>],
    ) -> Poll<std::io::Result<usize>> {
        Pin::new(&mut self.get_mut().io).poll_write_vectored(cx, bufs)
    }
    fn is_write_vectored(&self) -> bool {
        self.io.is_write_vectored()
    }
    fn poll_flush(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<std::io::Result<()>> {
        Pin::new(&mut self.get_mut().io).poll_flush(cx)
    }
    fn poll_shutdown(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<std::io::Result<()>> {
        Pin::new(&mut self.get_mut().io).poll_shutdown(cx)
    }
}

/// One generation: its connections' channel, its stop signal and its task.
struct Generation {
    conns: mpsc::Sender<Conn>,
    stop: oneshot::Sender<()>,
    task: tokio::task::JoinHandle<Result<(), tonic::transport::Error>>,
}

fn spawn(router: Router) -> Generation {
    let (conns, rx) = mpsc::channel::<Conn>(64);
    let (stop, stop_rx) = oneshot::channel::<()>();
    let task = tokio::spawn(
        router.serve_with_incoming_shutdown(ReceiverStream::new(rx), async {
            let _ = stop_rx.await;
        }),
    );
    Generation { conns, stop, task }
}

/// Accepts connections for the current generation; on a reload, starts the next and lets
/// the previous finish its connections; on stop, stops them all.
pub(super) async fn serve(
    listener: TcpListener,
    gate: Gate,
    first: Router,
    make: impl Fn(Option<tonic::transport::ServerTlsConfig>) -> anyhow::Result<Router>,
    mut reload: mpsc::Receiver<Reload>,
    mut stop: oneshot::Receiver<()>,
) -> Result<(), tonic::transport::Error> {
    let mut current = spawn(first);
    let mut old: Vec<Generation> = Vec::new();
    loop {
        tokio::select! {
            _ = &mut stop => break,
            r = reload.recv() => {
                let Some((tls, done)) = r else { break };
                match make(Some(tls)) {
                    Ok(router) => {
                        let previous = std::mem::replace(&mut current, spawn(router));
                        let _ = previous.stop.send(());
                        old.push(Generation { stop: oneshot::channel().0, ..previous });
                        old.retain(|g| !g.task.is_finished());
                        tracing::info!("TLS settings reloaded; open connections keep the old ones");
                        let _ = done.send(Ok(()));
                    }
                    Err(e) => {
                        tracing::warn!(error = %e, "TLS reload failed; the settings are unchanged");
                        let _ = done.send(Err(e));
                    }
                }
            }
            a = listener.accept() => match a {
                Ok((s, _)) => {
                    let _ = s.set_nodelay(true);
                    gate.admit(s, current.conns.clone());
                }
                Err(e) => {
                    tracing::warn!(error = %e, "accept failed");
                    tokio::time::sleep(std::time::Duration::from_millis(10)).await;
                }
            }
        }
    }
    let _ = current.stop.send(());
    let mut result = current.task.await.unwrap_or(Ok(()));
    for g in old {
        if let Ok(Err(e)) = g.task.await {
            result = Err(e);
        }
    }
    result
}

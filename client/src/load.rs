//! `load`: N concurrent clients, each streaming scenario sessions in lockstep, one after another
//! (round-robin over the selected scenarios), for a fixed duration; throughput, latency
//! percentiles and errors by code.

use crate::data::{Selection, load_selection};
use crate::messages::stream_messages;
use crate::pb;
use crate::replay::method_name;
use crate::session::{Client, SessionConfig, SessionEnd, connect_with, run_session};
use crate::stats::{Latencies, LatencyMs};
use anyhow::{Result, bail};
use std::collections::BTreeMap;
use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::Duration;
use tokio::time::Instant;

/// What `load` does.
#[derive(Debug, Clone)]
pub struct LoadOptions {
    /// Server URL, e.g. `http://127.0.0.1:50051`.
    pub server: String,
    /// Dataset directory.
    pub data: PathBuf,
    /// Scenarios the clients cycle through.
    pub selection: Selection,
    /// Method of every session.
    pub method: pb::Method,
    /// Concurrent clients (each one session at a time).
    pub concurrency: usize,
    /// How long to run.
    pub duration: Duration,
    /// HTTP/2 connections the clients share (client i uses connection i mod this).
    pub connections: usize,
    /// Surface points per `SurfaceBatch` (0: all in one).
    pub batch: usize,
    /// Options sent in each `SessionStart`.
    pub options: Option<pb::RegisterOptions>,
    /// Bearer token.
    pub token: Option<String>,
    /// Resume sessions whose stream is lost.
    pub resume: bool,
    /// Longest wait for a stream to open and for each answer.
    pub timeout: Duration,
    /// Pause after a failed session before the next (100 ms).
    pub backoff: Duration,
    /// At most this many messages per second per client (None: as fast as the answers come,
    /// a closed loop).
    pub rate_hz: Option<f64>,
    /// A progress line on stderr every few seconds.
    pub progress: bool,
    /// TLS settings.
    pub tls: crate::session::Tls,
}

impl Default for LoadOptions {
    fn default() -> Self {
        Self {
            server: "http://127.0.0.1:50051".into(),
            data: PathBuf::new(),
            selection: Selection::Spread(10),
            method: pb::Method::Libr,
            concurrency: 4,
            duration: Duration::from_secs(10),
            connections: 1,
            batch: 100,
            options: None,
            token: None,
            resume: false,
            timeout: Duration::from_secs(60),
            backoff: Duration::from_millis(100),
            rate_hz: None,
            progress: false,
            tls: crate::session::Tls::default(),
        }
    }
}

/// Session counts of a load test.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize)]
pub struct SessionCounts {
    /// Sessions started (streams the clients tried to open).
    pub started: u64,
    /// Sessions that received at least one update.
    pub admitted: u64,
    /// Sessions refused: failed to open or ended with a status before any update.
    pub refused: u64,
    /// Sessions whose every message was answered and that closed with OK.
    pub completed: u64,
    /// Admitted sessions that ended with an error (status, early close, timeout).
    pub failed: u64,
    /// Sessions cut by the end of the test.
    pub cut: u64,
}

/// What `load` measured (`load --json` prints it).
#[derive(Debug, Clone, Default, serde::Serialize)]
pub struct LoadSummary {
    /// Updates received (registrations and rejections): the requests served.
    pub requests: u64,
    /// Updates carrying a registration.
    pub registrations: u64,
    /// Updates carrying a rejection.
    pub rejections: u64,
    /// Requests per second of wall time.
    pub throughput_per_s: f64,
    /// Registrations per second of wall time.
    pub registrations_per_s: f64,
    /// Wall time of the test (s).
    pub duration_s: f64,
    /// Concurrent clients.
    pub concurrency: usize,
    /// Method of the sessions.
    pub method: String,
    /// Scenarios cycled through.
    pub scenarios: usize,
    /// Latency of every answer.
    pub latency_ms: LatencyMs,
    /// Latency of the answers that carried a registration (admitted work only).
    pub latency_registration_ms: LatencyMs,
    /// Errors by code: sessions ending with a gRPC status (by its code name), client-side
    /// timeouts (`DEADLINE_EXCEEDED`), early closes (`CLOSED_EARLY`), and in-band rejections
    /// (by their `code`).
    pub errors: BTreeMap<String, u64>,
    /// The session-level part of `errors`.
    pub session_errors: BTreeMap<String, u64>,
    /// The rejection part of `errors`.
    pub rejections_by_code: BTreeMap<String, u64>,
    /// Sessions.
    pub sessions: SessionCounts,
    /// Registrations by quality (`QUALITY_OK`, `QUALITY_DEGRADED`, ...) and by the method that
    /// produced them (`METHOD_LIBR`, `METHOD_RIGID` when LIBR degraded to it).
    pub quality: BTreeMap<String, u64>,
    /// Registrations by the method that produced them.
    pub method_used: BTreeMap<String, u64>,
}

#[derive(Default)]
struct TaskStats {
    latency: Latencies,
    latency_registration: Latencies,
    requests: u64,
    registrations: u64,
    rejections_by_code: BTreeMap<String, u64>,
    session_errors: BTreeMap<String, u64>,
    sessions: SessionCounts,
    quality: BTreeMap<String, u64>,
    method_used: BTreeMap<String, u64>,
}

async fn client_task(
    client: Client,
    sessions: Arc<Vec<Vec<pb::StreamRegisterRequest>>>,
    next: Arc<AtomicUsize>,
    cfg: SessionConfig,
    backoff: Duration,
) -> TaskStats {
    let deadline = cfg.deadline.expect("load sessions have a deadline");
    let mut st = TaskStats::default();
    while Instant::now() < deadline {
        let msgs = &sessions[next.fetch_add(1, Ordering::Relaxed) % sessions.len()];
        st.sessions.started += 1;
        let (mut requests, mut registrations) = (0u64, 0u64);
        let (lat, lat_reg, rej, quality, used) = (
            &mut st.latency,
            &mut st.latency_registration,
            &mut st.rejections_by_code,
            &mut st.quality,
            &mut st.method_used,
        );
        let out = run_session(&client, msgs, &cfg, |u, l| {
            requests += 1;
            let is_reg = matches!(u.update, Some(pb::stream_update::Update::Registration(_)));
            if is_reg {
                registrations += 1;
            }
            if let Some(pb::stream_update::Update::Rejection(r)) = &u.update {
                *rej.entry(r.code.clone()).or_default() += 1;
            }
            if let Some(pb::stream_update::Update::Registration(r)) = &u.update {
                *quality
                    .entry(r.quality().as_str_name().to_string())
                    .or_default() += 1;
                *used
                    .entry(r.method_used().as_str_name().to_string())
                    .or_default() += 1;
            }
            if let Some(l) = l {
                lat.record(l);
                if is_reg {
                    lat_reg.record(l);
                }
            }
        })
        .await;
        st.requests += requests;
        st.registrations += registrations;
        if out.updates > 0 {
            st.sessions.admitted += 1;
        }
        match &out.end {
            SessionEnd::Completed => st.sessions.completed += 1,
            SessionEnd::Cut => st.sessions.cut += 1,
            SessionEnd::Refused(_) => st.sessions.refused += 1,
            _ if out.updates == 0 => st.sessions.refused += 1,
            _ => st.sessions.failed += 1,
        }
        if let Some(code) = out.end.error_code() {
            *st.session_errors.entry(code.to_string()).or_default() += 1;
            let wake = Instant::now() + backoff;
            if wake >= deadline {
                break;
            }
            tokio::time::sleep_until(wake).await;
        }
    }
    st
}

/// Runs the load test: `concurrency` clients, each opening sessions one after another on the
/// next scenario (round-robin, shared), sending in lockstep, until `duration` ends; a failed
/// session counts one error under its code and its client pauses `backoff` before the next.
pub async fn load(opts: &LoadOptions) -> Result<LoadSummary> {
    if opts.concurrency == 0 {
        bail!("--concurrency must be at least 1");
    }
    let loaded = load_selection(&opts.data, &opts.selection, false)?;
    if loaded.scenarios.is_empty() {
        bail!("no scenarios selected in {}", opts.data.display());
    }
    let sessions: Arc<Vec<_>> = Arc::new(
        loaded
            .scenarios
            .iter()
            .map(|s| {
                stream_messages(
                    &s.case_id,
                    opts.method,
                    opts.options,
                    &s.scenario,
                    &s.planes,
                    opts.batch,
                )
            })
            .collect(),
    );
    let mut clients = Vec::new();
    for _ in 0..opts.connections.max(1) {
        clients.push(connect_with(&opts.server, &opts.tls).await?);
    }
    let mut cfg = SessionConfig::new(opts.timeout, opts.token.as_deref())?;
    cfg.resume = opts.resume.then(crate::session::Resume::default);
    let t0 = Instant::now();
    cfg.deadline = Some(t0 + opts.duration);
    cfg.rate_hz = opts.rate_hz;
    let next = Arc::new(AtomicUsize::new(0));
    let tasks: Vec<_> = (0..opts.concurrency)
        .map(|i| {
            tokio::spawn(client_task(
                clients[i % clients.len()].clone(),
                sessions.clone(),
                next.clone(),
                cfg.clone(),
                opts.backoff,
            ))
        })
        .collect();
    let progress = opts.progress.then(|| {
        tokio::spawn(async move {
            let mut tick = tokio::time::interval(Duration::from_secs(5));
            tick.tick().await;
            loop {
                tick.tick().await;
                eprintln!("load: {:.0} s", t0.elapsed().as_secs_f64());
            }
        })
    });
    let mut total = TaskStats::default();
    for t in tasks {
        let st = t.await?;
        total.latency.merge(&st.latency);
        total.latency_registration.merge(&st.latency_registration);
        total.requests += st.requests;
        total.registrations += st.registrations;
        for (k, v) in st.rejections_by_code {
            *total.rejections_by_code.entry(k).or_default() += v;
        }
        for (k, v) in st.session_errors {
            *total.session_errors.entry(k).or_default() += v;
        }
        for (k, v) in st.quality {
            *total.quality.entry(k).or_default() += v;
        }
        for (k, v) in st.method_used {
            *total.method_used.entry(k).or_default() += v;
        }
        let (a, b) = (&mut total.sessions, &st.sessions);
        a.started += b.started;
        a.admitted += b.admitted;
        a.refused += b.refused;
        a.completed += b.completed;
        a.failed += b.failed;
        a.cut += b.cut;
    }
    if let Some(p) = progress {
        p.abort();
    }
    let secs = t0.elapsed().as_secs_f64().max(1e-9);
    let mut errors = total.session_errors.clone();
    for (k, v) in &total.rejections_by_code {
        *errors.entry(k.clone()).or_default() += v;
    }
    Ok(LoadSummary {
        requests: total.requests,
        registrations: total.registrations,
        rejections: total.rejections_by_code.values().sum(),
        throughput_per_s: total.requests as f64 / secs,
        registrations_per_s: total.registrations as f64 / secs,
        duration_s: secs,
        concurrency: opts.concurrency,
        method: method_name(opts.method).to_string(),
        scenarios: sessions.len(),
        latency_ms: total.latency.summary(),
        latency_registration_ms: total.latency_registration.summary(),
        errors,
        session_errors: total.session_errors,
        rejections_by_code: total.rejections_by_code,
        sessions: total.sessions,
        quality: total.quality,
        method_used: total.method_used,
    })
}

fn counts(m: &BTreeMap<String, u64>) -> String {
    if m.is_empty() {
        return "none".into();
    }
    m.iter()
        .map(|(k, v)| format!("{k} {v}"))
        .collect::<Vec<_>>()
        .join(", ")
}

/// The summary as readable text.
pub fn load_table(s: &LoadSummary) -> String {
    let l = &s.latency_ms;
    let r = &s.latency_registration_ms;
    let errors: Vec<String> = s.errors.iter().map(|(k, v)| format!("{k} {v}")).collect();
    let c = &s.sessions;
    format!(
        "{} requests in {:.1} s ({:.1}/s; {} registrations, {:.1}/s) from {} clients, method {}, {} scenarios\n\
         latency p50 {:.1} ms, p95 {:.1} ms, p99 {:.1} ms, max {:.1} ms (registrations only: p50 {:.1}, p95 {:.1}, p99 {:.1}, max {:.1})\n\
         sessions: {} started, {} admitted, {} refused, {} completed, {} failed, {} cut at the end\n\
         quality: {}; produced by: {}\n\
         errors: {}\n",
        s.requests,
        s.duration_s,
        s.throughput_per_s,
        s.registrations,
        s.registrations_per_s,
        s.concurrency,
        s.method,
        s.scenarios,
        l.p50,
        l.p95,
        l.p99,
        l.max,
        r.p50,
        r.p95,
        r.p99,
        r.max,
        c.started,
        c.admitted,
        c.refused,
        c.completed,
        c.failed,
        c.cut,
        counts(&s.quality),
        counts(&s.method_used),
        if errors.is_empty() {
            "none".to_string()
        } else {
            errors.join(", ")
        }
    )
}

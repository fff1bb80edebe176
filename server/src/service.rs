//! The `librplus.v1.LibRPlus` service: case listing, unary and streamed registration, with
//! admission control, limits, deadlines and drain on shutdown.

use crate::audit::Record;
use crate::auth::{Principal, Role};
use crate::cases::Case;
use crate::compute::Job;
use crate::convert::{code_name, measurements_from_pb};
use crate::error::{ServiceError, Unavailable, short};
use crate::session::records::audit_record;
use crate::session::state::{check_method, options as checked_options};
pub use crate::shared::{MAX_CASE_ID, Shared};
use crate::shared::{count_error, random_u64};
use librplus_proto::v1 as pb;
use pb::lib_r_plus_server::LibRPlus;
use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};
use tokio::sync::mpsc;
use tokio_stream::wrappers::ReceiverStream;
use tonic::{Request, Response, Status, Streaming};
use tracing::Instrument;

/// The service.
#[derive(Clone)]
pub struct Svc(pub Arc<Shared>);

fn fail(b: ServiceError) -> Status {
    count_error(b.code());
    b.to_status()
}

/// The client's deadline from the `grpc-timeout` header, if any.
pub fn grpc_timeout(md: &tonic::metadata::MetadataMap) -> Option<Duration> {
    let v = md.get("grpc-timeout")?.to_str().ok()?;
    if v.len() < 2 {
        return None;
    }
    let (num, unit) = v.split_at(v.len() - 1);
    let n: u64 = num.parse().ok()?;
    Some(match unit {
        "H" => Duration::from_secs(n.saturating_mul(3600)),
        "M" => Duration::from_secs(n.saturating_mul(60)),
        "S" => Duration::from_secs(n),
        "m" => Duration::from_millis(n),
        "u" => Duration::from_micros(n),
        "n" => Duration::from_nanos(n),
        _ => return None,
    })
}

impl Svc {
    /// The caller of `rpc` (refusals are audited).
    /// Its connection is marked as used, and as authenticated when the caller is.
    fn caller<T>(&self, req: &Request<T>, rpc: &str) -> Result<Arc<Principal>, Status> {
        let certs = req.peer_certs();
        let who = self
            .0
            .caller(req.metadata(), certs.as_deref().map(Vec::as_slice));
        self.0.connections.called(req.remote_addr(), who.is_ok());
        who.map_err(|e| {
            self.0.refused(rpc, "", None, &e);
            fail(e)
        })
    }

    /// `who` may call `rpc` (it holds `role`); refusals are audited.
    fn allowed(&self, who: &Principal, role: Role, rpc: &str, what: &str) -> Result<(), Status> {
        who.require(role, what).map_err(|e| {
            self.0.refused(rpc, &who.name, None, &e);
            fail(e)
        })
    }
}

fn summary(c: &Case) -> pb::CaseSummary {
    let m = &c.prepared.model.mesh;
    pb::CaseSummary {
        case_id: c.id.clone(),
        source: c.source.display().to_string(),
        node_count: m.num_nodes() as u32,
        tet_count: m.num_tets() as u32,
        libr_ready: c.prepared.basis.is_some(),
        libr_plus_ready: c.prepared.librplus.is_some(),
        v2s_ready: c.prepared.v2s.is_some(),
        default_method: crate::convert::method_to_pb(c.default_method) as i32,
        preload_seconds: c.prepared.seconds,
        basis_from_cache: c.prepared.basis_from_cache,
        effects: crate::convert::effects(&c.prepared),
    }
}

type UpdateStream = ReceiverStream<Result<pb::StreamUpdate, Status>>;

#[tonic::async_trait]
impl LibRPlus for Svc {
    async fn list_cases(
        &self,
        req: Request<pb::ListCasesRequest>,
    ) -> Result<Response<pb::ListCasesResponse>, Status> {
        let who = self.caller(&req, "ListCases")?;
        self.allowed(&who, Role::Read, "ListCases", "list cases")?;
        let cases = crate::access::cases(&self.0).map_err(fail)?;
        let mut out: Vec<pb::CaseSummary> = cases
            .values()
            .filter(|c| who.may_use(&c.id))
            .map(|c| summary(c))
            .collect();
        // Uploaded cases out of memory while idle are listed too (loaded when asked for).
        if let Some(store) = &self.0.store {
            for st in self.0.registry.all() {
                if st.state == pb::CaseState::Stored as i32
                    && who.may_use(&st.case_id)
                    && let Some(s) = store.find(&st.case_id)
                {
                    out.push(pb::CaseSummary {
                        case_id: st.case_id.clone(),
                        source: "case store (idle, not in memory: loaded when asked for)".into(),
                        node_count: s.nodes as u32,
                        tet_count: s.tets as u32,
                        ..Default::default()
                    });
                }
            }
            out.sort_by(|a, b| a.case_id.cmp(&b.case_id));
        }
        Ok(Response::new(pb::ListCasesResponse { cases: out }))
    }

    async fn describe_case(
        &self,
        req: Request<pb::DescribeCaseRequest>,
    ) -> Result<Response<pb::DescribeCaseResponse>, Status> {
        let who = self.caller(&req, "DescribeCase")?;
        self.allowed(&who, Role::Read, "DescribeCase", "describe cases")?;
        let pb::DescribeCaseRequest {
            case_id,
            include_mesh,
        } = req.into_inner();
        // An upload still loading, or failed: its state only.
        if crate::access::visible(&case_id, &who)
            && !crate::access::cases(&self.0)
                .map_err(fail)?
                .contains_key(&case_id)
            && let Some(status) = self.0.registry.status(&case_id)
        {
            return Ok(Response::new(pb::DescribeCaseResponse {
                status: Some(status),
                length_unit: "mm".into(),
                frame: "image (preoperative), LPS".into(),
                ..Default::default()
            }));
        }
        let c = crate::access::case(&self.0, &case_id, "case_id", &who).map_err(|e| {
            self.0
                .refused("DescribeCase", &who.name, Some(&case_id), &e);
            fail(e)
        })?;
        let mut out = pb::DescribeCaseResponse {
            summary: Some(summary(&c)),
            status: Some(crate::registry::ready_status(&c)),
            length_unit: "mm".into(),
            frame: "image (preoperative), LPS".into(),
            ..Default::default()
        };
        if include_mesh {
            let model = &c.prepared.model;
            out.nodes_mm = model.mesh.nodes().iter().flatten().copied().collect();
            out.tets = model.mesh.tets().iter().flatten().copied().collect();
            out.node_labels = (0..model.mesh.num_nodes())
                .map(|i| {
                    [
                        (model.anterior[i], pb::NodeLabel::Anterior),
                        (model.posterior[i], pb::NodeLabel::Posterior),
                        (model.falciform[i], pb::NodeLabel::Falciform),
                        (model.inferior_ridge[i], pb::NodeLabel::InferiorRidge),
                    ]
                    .iter()
                    .filter(|(on, _)| *on)
                    .fold(0u32, |acc, (_, bit)| acc | *bit as u32)
                })
                .collect();
            out.vessel_points_mm = model.vessel_points.iter().flatten().copied().collect();
            out.vessel_segments = model.vessel_segments.iter().flatten().copied().collect();
        }
        Ok(Response::new(out))
    }

    async fn register(
        &self,
        req: Request<pb::RegisterRequest>,
    ) -> Result<Response<pb::Registration>, Status> {
        let arrival = Instant::now();
        if *self.0.drain.borrow() {
            return Err(fail(Unavailable::ShuttingDown.into()));
        }
        let client_deadline = grpc_timeout(req.metadata());
        let who = self.caller(&req, "Register")?;
        self.allowed(&who, Role::Register, "Register", "register")?;
        // Fairness between clients: the principal and its connection.
        let client = format!(
            "{}@{}",
            who.name,
            req.remote_addr()
                .map_or_else(|| "?".to_string(), |a| a.to_string())
        );
        // Every field, so that a new one breaks the build until it is handled.
        let pb::RegisterRequest {
            case_id,
            method,
            measurements,
            options,
        } = req.into_inner();
        let run = async {
            let case = crate::access::case(&self.0, &case_id, "case_id", &who)?;
            // A registration is a use (an idle upload leaves memory; describing it is not).
            case.touch();
            let method = check_method(&case, method, "method")?;
            let m = measurements
                .as_ref()
                .ok_or_else(|| ServiceError::field("measurements", "is missing"))?;
            let checked =
                measurements_from_pb(m, "measurements", self.0.config.max_points_per_message)?;
            let mut options = checked_options(&self.0.config, options.as_ref(), "options")?;
            if let Some(d) = client_deadline {
                // Answer before the client gives up: keep 10% (at least 5 ms) for the reply.
                options.budget = options
                    .budget
                    .min(d.mul_f64(0.9).saturating_sub(Duration::from_millis(5)));
            }
            let job = Job {
                case,
                request: crate::compute::Request {
                    measurements: checked,
                    method,
                    options,
                },
                arrival,
                prepared: None,
                first: None,
            };
            let reg = self.0.engine.run(job, Some(&client)).await?;
            // Acknowledged only once recorded.
            if self.0.audit.is_some() {
                let mut rec = audit_record(&reg, &who.name, &case_id, None, 0);
                rec.measurements = measurements.as_ref().map(prost::Message::encode_to_vec);
                self.0
                    .record(vec![Record::Registration(Box::new(rec))])
                    .await?;
            }
            Ok(reg)
        };
        let span =
            tracing::info_span!("register", case = %short(&case_id, 64), principal = %who.name);
        match run.instrument(span).await {
            Ok(reg) => Ok(Response::new(reg)),
            Err(b) => {
                self.0.refused("Register", &who.name, Some(&case_id), &b);
                tracing::info!(code = code_name(b.code()), message = %short(b.to_status().message(), 200), "register refused");
                Err(fail(b))
            }
        }
    }

    async fn create_case(
        &self,
        req: Request<Streaming<pb::CreateCaseRequest>>,
    ) -> Result<Response<pb::CreateCaseResponse>, Status> {
        let who = self.caller(&req, "CreateCase")?;
        self.allowed(&who, Role::Manage, "CreateCase", "upload cases")?;
        let r = crate::upload::create(&self.0, &who, req.into_inner()).await;
        r.map(Response::new).map_err(|e| {
            self.0.refused("CreateCase", &who.name, None, &e);
            fail(e)
        })
    }

    type WatchCaseStream = ReceiverStream<Result<pb::CaseStatus, Status>>;

    async fn watch_case(
        &self,
        req: Request<pb::WatchCaseRequest>,
    ) -> Result<Response<Self::WatchCaseStream>, Status> {
        let who = self.caller(&req, "WatchCase")?;
        self.allowed(&who, Role::Read, "WatchCase", "watch cases")?;
        let pb::WatchCaseRequest { case_id } = req.into_inner();
        crate::access::cases(&self.0).map_err(fail)?;
        let rx = crate::access::visible(&case_id, &who)
            .then(|| self.0.registry.watch(&case_id))
            .flatten();
        let Some(mut rx) = rx else {
            return Err(fail(crate::access::not_found(
                &self.0, &case_id, "case_id", &who,
            )));
        };
        let (tx, out) = mpsc::channel(4);
        let mut drain = self.0.drain.clone();
        tokio::spawn(async move {
            loop {
                let s = rx.borrow_and_update().clone();
                // A case READY on a coarse basis is followed on to its own basis.
                let done = s.state != pb::CaseState::Loading as i32 && !s.coarse_basis;
                if tx.send(Ok(s)).await.is_err() || done {
                    return;
                }
                let changed = tokio::select! {
                    r = rx.changed() => Some(r.is_ok()),
                    _ = drain.wait_for(|d| *d) => None,
                };
                match changed {
                    Some(true) => {}
                    Some(false) => return,
                    None => {
                        let _ = tx
                            .send(Err(Status::unavailable("the server is shutting down")))
                            .await;
                        return;
                    }
                }
            }
        });
        Ok(Response::new(ReceiverStream::new(out)))
    }

    async fn delete_case(
        &self,
        req: Request<pb::DeleteCaseRequest>,
    ) -> Result<Response<pb::DeleteCaseResponse>, Status> {
        let who = self.caller(&req, "DeleteCase")?;
        self.allowed(&who, Role::Manage, "DeleteCase", "delete cases")?;
        let pb::DeleteCaseRequest { case_id } = req.into_inner();
        let r = crate::upload::delete(&self.0, &who, &case_id).await;
        r.map(Response::new).map_err(|e| {
            self.0.refused("DeleteCase", &who.name, Some(&case_id), &e);
            fail(e)
        })
    }

    type StreamRegisterStream = UpdateStream;

    async fn stream_register(
        &self,
        req: Request<Streaming<pb::StreamRegisterRequest>>,
    ) -> Result<Response<Self::StreamRegisterStream>, Status> {
        if *self.0.drain.borrow() {
            return Err(fail(Unavailable::ShuttingDown.into()));
        }
        crate::access::cases(&self.0).map_err(fail)?;
        let who = self.caller(&req, "StreamRegister")?;
        self.allowed(&who, Role::Register, "StreamRegister", "register")?;
        // The session's slot is taken when its SessionStart arrives (a stream that never
        // starts holds none, and is closed after `session_start_timeout_s`).
        let deadline = grpc_timeout(req.metadata()).map(|d| Instant::now() + d);
        // The run's prefix, a counter (unique) and 48 random bits (not guessable).
        let sid = format!(
            "s{}-{:06}{:015}",
            self.0.boot,
            self.0.next_session.fetch_add(1, Ordering::Relaxed) + 1,
            random_u64() % 1_000_000_000_000_000
        );
        let inbound = req.into_inner();
        let (tx, rx) = mpsc::channel(8);
        let span = tracing::info_span!("session", session_id = %sid, principal = %who.name);
        let serve = crate::session::serve(self.0.clone(), who, inbound, tx, deadline, sid);
        tokio::spawn(serve.instrument(span));
        Ok(Response::new(ReceiverStream::new(rx)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn grpc_timeout_headers_parse() {
        let mut md = tonic::metadata::MetadataMap::new();
        assert_eq!(grpc_timeout(&md), None);
        for (v, d) in [
            ("250m", Duration::from_millis(250)),
            ("3S", Duration::from_secs(3)),
            ("2M", Duration::from_secs(120)),
            ("1H", Duration::from_secs(3600)),
            ("500u", Duration::from_micros(500)),
            ("7n", Duration::from_nanos(7)),
        ] {
            md.insert("grpc-timeout", v.parse().unwrap());
            assert_eq!(grpc_timeout(&md), Some(d), "{v}");
        }
        for bad in ["", "m", "12x", "-5m"] {
            md.insert("grpc-timeout", bad.parse().unwrap());
            assert_eq!(grpc_timeout(&md), None, "{bad}");
        }
    }
}

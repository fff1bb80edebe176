//! METHOD_NONLINEAR in a stream: the linear answer at once, its refinement after it for the
//! same client_seq; a stream lost between the two resumes to both again; one answer when the
//! client asks for one; the refinement skipped, and said so, when the budget cannot hold it;
//! the audit log keeps both answers.

use crate::common::*;
use librplus_server::audit;

fn registration(u: &pb::StreamUpdate) -> &pb::Registration {
    match &u.update {
        Some(pb::stream_update::Update::Registration(r)) => r,
        other => panic!("expected a registration, got {other:?}"),
    }
}

/// The start of a METHOD_NONLINEAR session (its options as given), or of its resume.
fn start(
    msgs: &[pb::StreamRegisterRequest],
    options: pb::RegisterOptions,
) -> pb::StreamRegisterRequest {
    let mut m = msgs[0].clone();
    if let Some(pb::stream_register_request::Msg::Start(s)) = &mut m.msg {
        s.method = pb::Method::Nonlinear as i32;
        s.options = Some(options);
    }
    m
}

fn resume(sid: &str) -> pb::StreamRegisterRequest {
    pb::StreamRegisterRequest {
        client_seq: 1,
        msg: Some(pb::stream_register_request::Msg::Start(pb::SessionStart {
            resume_session_id: sid.into(),
            ..Default::default()
        })),
    }
}

/// Largest difference of two answers' transforms and displacements.
fn diff(a: &pb::Registration, b: &pb::Registration) -> f64 {
    let (ta, tb) = (
        a.image_to_physical.as_ref().unwrap(),
        b.image_to_physical.as_ref().unwrap(),
    );
    let t = ta.rotation.iter().zip(&tb.rotation);
    let t = t.chain(ta.translation_mm.iter().zip(&tb.translation_mm));
    let u = a.displacement_mm.iter().zip(&b.displacement_mm);
    t.map(|(x, y)| (x - y).abs())
        .chain(u.map(|(x, y)| f64::from((x - y).abs())))
        .fold(0.0, f64::max)
}

/// The two answers of one message: the linear one flagged `follows`, then the refinement
/// flagged `refines`, both for `seq`.
async fn both(s: &mut Stream, seq: u64) -> (pb::Registration, pb::Registration) {
    let u1 = s.rx.message().await.unwrap().unwrap();
    let u2 = s.rx.message().await.unwrap().unwrap();
    assert_eq!((u1.last_client_seq, u2.last_client_seq), (seq, seq));
    let (a, b) = (registration(&u1).clone(), registration(&u2).clone());
    check_pair(&a, &b);
    (a, b)
}

fn check_pair(a: &pb::Registration, b: &pb::Registration) {
    let (ra, rb) = (
        a.refinement.as_ref().unwrap(),
        b.refinement.as_ref().unwrap(),
    );
    assert!(ra.follows && !ra.refines, "{ra:?}");
    assert!(rb.refines && !rb.follows, "{rb:?}");
    assert_eq!(a.method_used(), pb::Method::Adaptive);
    assert_eq!(b.method_used(), pb::Method::Nonlinear);
    assert!(rb.linear_objective_mm2 > 0.0 && rb.solves > 0, "{rb:?}");
    // The refined answer is the refinement's own only when it fits better; else the linear one.
    if rb.kept_linear.is_empty() {
        assert!(rb.refined_objective_mm2 < rb.linear_objective_mm2, "{rb:?}");
    } else {
        assert!(
            diff(a, b) <= 1e-9,
            "kept the linear answer, yet differs by {}",
            diff(a, b)
        );
    }
    let total = |r: &pb::Registration| r.timings.as_ref().unwrap().total_ms;
    assert!(total(a) <= total(b));
    eprintln!(
        "linear {:.3} mm², refined {:.3} mm², change {:.2} mm RMS, {} solves, {:.0} ms; kept linear: {:?}",
        rb.linear_objective_mm2,
        rb.refined_objective_mm2,
        rb.change_rms_mm,
        rb.solves,
        rb.refine_ms,
        rb.kept_linear
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn nonlinear_answers_twice_resumes_between_the_answers_and_answers_once_when_asked() {
    let dir = tempfile::tempdir().unwrap();
    let db = dir.path().join("audit.db");
    let cfg = ServerConfig {
        audit_db: Some(db.clone()),
        ..config(4)
    };
    let mut running = librplus_server::start(cfg).await.unwrap();
    running.ready().await.unwrap();
    let mut c = client(running.addr).await;
    let case = open(dataset()).unwrap().deformations[0].geometry.clone();
    let (_, sc) = scenario("surface+2us");
    let (msgs, _) = stream_of(&case, &sc, pb::Method::Nonlinear);
    assert!(msgs.len() >= 3);
    let generous = pb::RegisterOptions {
        time_budget_ms: 100_000,
        ..Default::default()
    };

    // Two answers for one message.
    let mut s = open_stream(&mut c, start(&msgs, generous)).await.unwrap();
    s.tx.send(msgs[1].clone()).await.unwrap();
    let (_, refined_2) = both(&mut s, 2).await;
    // The next message's linear answer, then the stream lost before its refinement.
    s.tx.send(msgs[2].clone()).await.unwrap();
    let u = s.rx.message().await.unwrap().unwrap();
    let sid = u.session_id.clone();
    let linear_3 = registration(&u).clone();
    assert!(linear_3.refinement.as_ref().unwrap().follows);
    drop(s);
    // Resumed: both answers of the recorded messages again, the linear one as first sent.
    let mut r = open_stream(&mut c, resume(&sid)).await.unwrap();
    let (again, _) = both(&mut r, 3).await;
    assert!(
        diff(&again, &linear_3) <= 1e-9,
        "{}",
        diff(&again, &linear_3)
    );
    drop(r);

    // One answer when asked: the refined one, as the two-answer session's second.
    let single = pb::RegisterOptions {
        single_answer: true,
        ..generous
    };
    let mut s = open_stream(&mut c, start(&msgs, single)).await.unwrap();
    let u = s.send(msgs[1].clone()).await.unwrap();
    let one = registration(&u);
    let ri = one.refinement.as_ref().unwrap();
    assert!(!ri.follows && !ri.refines, "{ri:?}");
    assert_eq!(one.method_used(), pb::Method::Nonlinear);
    assert!(diff(one, &refined_2) <= 1e-9, "{}", diff(one, &refined_2));
    drop(s.tx);
    assert!(s.rx.message().await.unwrap().is_none(), "a second answer");

    // A budget that cannot hold the refinement: one answer, the linear fit, flagged, saying so.
    // The refinements above taught the case's estimate what one costs (about a second here).
    let tight = pb::RegisterOptions {
        time_budget_ms: 300,
        ..Default::default()
    };
    let mut s = open_stream(&mut c, start(&msgs, tight)).await.unwrap();
    let u = s.send(msgs[1].clone()).await.unwrap();
    let one = registration(&u);
    assert_eq!(one.method_used(), pb::Method::Adaptive);
    // Degraded, or worse where the error estimate says so (40 points of one patch).
    assert_ne!(one.quality(), pb::Quality::Ok, "{}", one.quality_reason);
    let ri = one.refinement.as_ref().unwrap();
    assert!(!ri.follows && !ri.refines && ri.solves == 0, "{ri:?}");
    assert!(
        ri.kept_linear.contains("nonlinear refinement needs"),
        "{ri:?}"
    );
    eprintln!(
        "skipped: {}; quality {:?}: {}",
        ri.kept_linear,
        one.quality(),
        one.quality_reason
    );
    drop(s.tx);
    assert!(s.rx.message().await.unwrap().is_none(), "a second answer");
    running.shutdown().await;

    // The audit log keeps both answers of each message, the linear and the refined one.
    let conn = audit::open_db(&db).unwrap();
    let rows = audit::rows(&conn, None, None).unwrap();
    let of = |seq: i64| -> Vec<String> {
        let regs = rows.iter().filter(|r| r.kind == "registration");
        regs.filter(|r| r.session_id.as_deref() == Some(sid.as_str()))
            .filter(|r| r.detail["client_seq"].as_i64() == Some(seq))
            .map(|r| r.detail["method"].as_str().unwrap_or("").to_string())
            .collect()
    };
    assert_eq!(of(2), ["METHOD_ADAPTIVE", "METHOD_NONLINEAR"]);
    // Message 3: the first stream's linear answer (and its refinement, recorded before the
    // send found the client gone), then the resume's two.
    let three = of(3);
    assert!(three.len() >= 3, "{three:?}");
    assert_eq!(
        three.iter().filter(|m| *m == "METHOD_ADAPTIVE").count(),
        2,
        "{three:?}"
    );
}

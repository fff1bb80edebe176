//! Bad input of every kind gets its status and the field it names, while the session and the server go on.

use crate::common::*;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_unary_input_gets_its_status_and_field() {
    let (running, mut c) = server(4).await;
    let (_, sc) = scenario("surface");
    let case = open(dataset()).unwrap().deformations[0].geometry.clone();
    let good = measurements_pb(&sc.measurements);
    let mut cases: Vec<(&str, pb::RegisterRequest, Code, Option<&str>)> = Vec::new();
    // A NaN in point 17's y: the field path names the point.
    assert!(good.xyz_mm.len() >= 3 * 18, "the scenario has 18 points");
    let mut nan = good.clone();
    nan.xyz_mm[3 * 17 + 1] = f64::NAN;
    cases.push((
        "NaN",
        request(&case, pb::Method::Libr, nan),
        Code::InvalidArgument,
        Some("measurements.points[17]"),
    ));
    let empty = pb::Measurements {
        xyz_mm: vec![],
        kind: vec![],
        ..good.clone()
    };
    cases.push((
        "empty",
        request(&case, pb::Method::Libr, empty),
        Code::InvalidArgument,
        Some("measurements.xyz_mm"),
    ));
    let mut ragged = good.clone();
    ragged.xyz_mm.pop();
    cases.push((
        "ragged",
        request(&case, pb::Method::Libr, ragged),
        Code::InvalidArgument,
        Some("measurements.xyz_mm"),
    ));
    let mut kinds = good.clone();
    kinds.kind.pop();
    cases.push((
        "kind count",
        request(&case, pb::Method::Libr, kinds),
        Code::InvalidArgument,
        Some("measurements.kind"),
    ));
    let mut unspecified = good.clone();
    unspecified.kind[0] = 0;
    cases.push((
        "kind unspecified",
        request(&case, pb::Method::Libr, unspecified),
        Code::InvalidArgument,
        Some("measurements.kind[0]"),
    ));
    let mut many = good.clone();
    while many.xyz_mm.len() / 3 <= 5_000 {
        many.xyz_mm.extend_from_slice(&good.xyz_mm);
        many.kind.extend_from_slice(&good.kind);
    }
    many.feature.clear();
    cases.push((
        "too many points",
        request(&case, pb::Method::Libr, many),
        Code::InvalidArgument,
        Some("measurements.xyz_mm"),
    ));
    let mut rot = good.clone();
    rot.initial_alignment.as_mut().unwrap().rotation[0] = 2.0;
    cases.push((
        "not a rotation",
        request(&case, pb::Method::Libr, rot),
        Code::InvalidArgument,
        Some("measurements.initial_alignment.rotation"),
    ));
    cases.push((
        "unknown case",
        request("nope", pb::Method::Libr, good.clone()),
        Code::NotFound,
        Some("case_id"),
    ));
    cases.push((
        "LIBR+ without weights",
        request(&case, pb::Method::LibrPlus, good.clone()),
        Code::FailedPrecondition,
        None,
    ));
    cases.push((
        "V2S without a model",
        request(&case, pb::Method::V2s, good.clone()),
        Code::FailedPrecondition,
        None,
    ));
    let mut bad_method = request(&case, pb::Method::Libr, good.clone());
    bad_method.method = 17;
    cases.push((
        "unknown method",
        bad_method,
        Code::InvalidArgument,
        Some("method"),
    ));
    let mut far = good.clone();
    for x in far.xyz_mm.iter_mut() {
        *x += 1000.0;
    }
    cases.push((
        "points 1 m away",
        request(&case, pb::Method::Libr, far),
        Code::FailedPrecondition,
        None,
    ));
    let mut budget = request(&case, pb::Method::Libr, good.clone());
    budget.options = Some(pb::RegisterOptions {
        time_budget_ms: 1_000_000,
        omit_displacements: false,
        trusted_alignment_mm: 0.0,
        held: false,
        single_answer: false,
    });
    cases.push((
        "budget too large",
        budget,
        Code::InvalidArgument,
        Some("options.time_budget_ms"),
    ));
    for (name, req, code, field) in cases {
        let e = c.register(req).await.expect_err(name);
        eprintln!(
            "{name}: {:?} {:?} {:?}",
            e.code(),
            e.message(),
            violations(&e)
        );
        assert_eq!(e.code(), code, "{name}: {e:?}");
        if let Some(f) = field {
            assert!(
                violations(&e).iter().any(|v| v == f),
                "{name}: {:?}",
                violations(&e)
            );
        }
    }
    // All points on one spot: a flagged degenerate rigid result, not a deformation.
    let mut spot = good.clone();
    let p0 = [spot.xyz_mm[0], spot.xyz_mm[1], spot.xyz_mm[2]];
    for c3 in spot.xyz_mm.chunks_exact_mut(3) {
        c3.copy_from_slice(&p0);
    }
    let r = c
        .register(request(&case, pb::Method::Libr, spot))
        .await
        .unwrap()
        .into_inner();
    assert_eq!(r.quality(), pb::Quality::Degenerate, "{}", r.quality_reason);
    assert_eq!(r.method_used(), pb::Method::Rigid);
    assert!(r.displacement_mm.iter().all(|&x| x == 0.0));
    // The server is alive and answers a good request.
    let ok = c
        .register(request(&case, pb::Method::Rigid, good))
        .await
        .unwrap()
        .into_inner();
    assert_eq!(ok.method_used(), pb::Method::Rigid);
    assert_eq!(running.shutdown().await, 0);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_stream_input_is_rejected_and_the_session_goes_on() {
    use pb::stream_register_request::Msg;
    let (running, mut c) = server(4).await;
    let (_, sc) = scenario("surface+1us");
    let case = open(dataset()).unwrap().deformations[0].geometry.clone();
    let (msgs, _) = stream_of(&case, &sc, pb::Method::Rigid);
    // A session must start with a SessionStart; an unknown case ends it with NOT_FOUND.
    let mut not_start = msgs[1].clone();
    not_start.client_seq = 1;
    let e = match open_stream(&mut c, not_start).await {
        Err(e) => e,
        Ok(mut s) => s.rx.message().await.expect_err("must fail"),
    };
    assert_eq!(e.code(), Code::FailedPrecondition, "{e:?}");
    let mut unknown = msgs[0].clone();
    if let Some(Msg::Start(st)) = unknown.msg.as_mut() {
        st.case_id = "nope".into();
    }
    let e = match open_stream(&mut c, unknown).await {
        Err(e) => e,
        Ok(mut s) => s.rx.message().await.expect_err("must fail"),
    };
    assert_eq!(e.code(), Code::NotFound, "{e:?}");

    let mut s = open_stream(&mut c, msgs[0].clone()).await.unwrap();
    let first = msgs[1].clone();
    let u = s.send(first.clone()).await.unwrap();
    assert!(
        matches!(u.update, Some(pb::stream_update::Update::Registration(_))),
        "{u:?}"
    );
    let reject = |u: pb::StreamUpdate| -> pb::Rejection {
        match u.update {
            Some(pb::stream_update::Update::Rejection(r)) => r,
            other => panic!("expected a rejection, got {other:?}"),
        }
    };
    let mut next_seq = 10u64;
    let mut with_seq = |mut m: pb::StreamRegisterRequest| {
        next_seq += 1;
        m.client_seq = next_seq;
        m
    };
    // Duplicate and out-of-order client_seq.
    let r = reject(s.send(first.clone()).await.unwrap());
    assert_eq!(
        (r.code.as_str(), r.violations[0].field.as_str()),
        ("FAILED_PRECONDITION", "client_seq")
    );
    let mut older = first.clone();
    older.client_seq = 1;
    let r = reject(s.send(older).await.unwrap());
    assert_eq!(r.code, "FAILED_PRECONDITION");
    // NaN in a surface batch.
    let mut nan = with_seq(first.clone());
    if let Some(Msg::Surface(b)) = nan.msg.as_mut() {
        b.xyz_mm[2] = f64::INFINITY;
        b.acquired_at = Some(prost_types::Timestamp {
            seconds: 200,
            nanos: 0,
        });
    }
    let r = reject(s.send(nan).await.unwrap());
    assert_eq!(
        (r.code.as_str(), r.violations[0].field.as_str()),
        ("INVALID_ARGUMENT", "surface.points[0]")
    );
    // A frame acquired before the previous one.
    let mut late = with_seq(first.clone());
    if let Some(Msg::Surface(b)) = late.msg.as_mut() {
        b.acquired_at = Some(prost_types::Timestamp {
            seconds: 1,
            nanos: 0,
        });
    }
    let r = reject(s.send(late).await.unwrap());
    assert_eq!(
        (r.code.as_str(), r.violations[0].field.as_str()),
        ("FAILED_PRECONDITION", "surface.acquired_at")
    );
    // A second start, an empty message, an empty batch, a plane without a pose.
    let r = reject(s.send(with_seq(msgs[0].clone())).await.unwrap());
    assert_eq!(r.code, "FAILED_PRECONDITION");
    let r = reject(
        s.send(with_seq(pb::StreamRegisterRequest {
            client_seq: 0,
            msg: None,
        }))
        .await
        .unwrap(),
    );
    assert_eq!(r.violations[0].field, "msg");
    let empty = pb::StreamRegisterRequest {
        client_seq: 0,
        msg: Some(Msg::Surface(pb::SurfaceBatch {
            acquired_at: None,
            xyz_mm: vec![],
            feature: vec![],
        })),
    };
    let r = reject(s.send(with_seq(empty)).await.unwrap());
    assert_eq!(r.violations[0].field, "surface.xyz_mm");
    let poseless = pb::StreamRegisterRequest {
        client_seq: 0,
        msg: Some(Msg::Ultrasound(pb::UltrasoundPlane {
            acquired_at: None,
            plane_to_physical: None,
            contour_uv_mm: vec![1.0, 2.0],
            vessel_uv_mm: vec![],
        })),
    };
    let r = reject(s.send(with_seq(poseless)).await.unwrap());
    assert_eq!(r.violations[0].field, "ultrasound.plane_to_physical");
    // The session goes on: the next good message registers all points accepted so far.
    let mut good = with_seq(msgs[2].clone());
    if let Some(Msg::Surface(b)) = good.msg.as_mut() {
        b.acquired_at = Some(prost_types::Timestamp {
            seconds: 300,
            nanos: 0,
        });
    }
    if let Some(Msg::Ultrasound(p)) = good.msg.as_mut() {
        p.acquired_at = Some(prost_types::Timestamp {
            seconds: 300,
            nanos: 0,
        });
    }
    let u = s.send(good).await.unwrap();
    assert!(
        matches!(u.update, Some(pb::stream_update::Update::Registration(_))),
        "{u:?}"
    );
    drop(s);
    assert_eq!(running.shutdown().await, 0);
}

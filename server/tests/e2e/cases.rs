//! A folder of meshes served as a set of cases.

use crate::common::*;

/// `--cases` also takes a folder of preoperative meshes: a labelled `.vtu` (with its vessels
/// beside it) keeps its labels, a bare tet mesh is labelled from its geometry; each file is a case
/// named by its stem.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_folder_of_meshes_is_a_set_of_cases() {
    let m = open(dataset()).unwrap();
    let g = &m.geometries[0];
    let folder = tempfile::tempdir().unwrap();
    std::fs::copy(dataset().join(&g.preop), folder.path().join("labelled.vtu")).unwrap();
    std::fs::copy(
        dataset().join(&g.vessels),
        folder.path().join("labelled.vessels.vtp"),
    )
    .unwrap();
    let geo = load_geometry(dataset(), &m, &g.id).unwrap();
    librplus::mesh::io::write(
        folder.path().join("bare.vtu"),
        &geo.model.mesh.to_file(),
        Default::default(),
    )
    .unwrap();
    let mut running = librplus_server::start(ServerConfig {
        cases: vec![folder.path().to_path_buf()],
        ..config(2)
    })
    .await
    .unwrap();
    let report = running.ready().await.unwrap();
    assert_eq!(report.cases.len(), 2, "{report:?}");
    let mut c = client(running.addr).await;
    let list = c
        .list_cases(pb::ListCasesRequest {})
        .await
        .unwrap()
        .into_inner();
    let ids: Vec<&str> = list.cases.iter().map(|c| c.case_id.as_str()).collect();
    assert_eq!(ids, ["bare", "labelled"]);
    let describe = |id: &str| pb::DescribeCaseRequest {
        case_id: id.into(),
        include_mesh: true,
    };
    let labelled = c
        .describe_case(describe("labelled"))
        .await
        .unwrap()
        .into_inner();
    let bare = c
        .describe_case(describe("bare"))
        .await
        .unwrap()
        .into_inner();
    let count = |d: &pb::DescribeCaseResponse, bit: u32| {
        d.node_labels.iter().filter(|&&l| l & bit != 0).count()
    };
    assert_eq!(
        count(&labelled, 1),
        geo.model.anterior.iter().filter(|&&a| a).count()
    );
    assert_eq!(
        labelled.vessel_segments.len(),
        2 * geo.model.vessel_segments.len()
    );
    assert!(bare.vessel_points_mm.is_empty());
    // Automatic labels on the same geometry: the anterior and posterior sets are most of the
    // boundary, as the dataset's own labels (made by the same labeller) are.
    assert_eq!(count(&bare, 1), count(&labelled, 1));
    assert_eq!(count(&bare, 2), count(&labelled, 2));
    let (_, sc) = scenario("surface");
    let keep: Vec<usize> = (0..sc.measurements.points.len())
        .filter(|&i| sc.measurements.kind[i] != MeasuredKind::Vessel)
        .collect();
    let meas = sc.measurements.subset(&keep);
    let r = c
        .register(request("bare", pb::Method::Libr, measurements_pb(&meas)))
        .await
        .unwrap()
        .into_inner();
    assert_eq!(r.method_used(), pb::Method::Libr);
    assert_eq!(r.node_count as usize, geo.model.mesh.num_nodes());
    assert_eq!(running.shutdown().await, 0);
}

/// A case with its augmented model beside it (`NAME.physics.json`): the summary and every
/// registration name the effects, the answer equals the library's with the same physics (the
/// same code `librplus register --physics` runs) to f32 rounding, a trusted alignment sent in
/// the options is applied as the library applies it, and a bad one is refused naming the field.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_case_with_physics_registers_with_its_effects() {
    use librplus::register::physics::Physics;
    let m = open(dataset()).unwrap();
    let g = &m.geometries[0];
    let geo = load_geometry(dataset(), &m, &g.id).unwrap();
    let folder = tempfile::tempdir().unwrap();
    std::fs::copy(dataset().join(&g.preop), folder.path().join("held.vtu")).unwrap();
    std::fs::copy(
        dataset().join(&g.vessels),
        folder.path().join("held.vessels.vtp"),
    )
    .unwrap();
    // Held at a posterior spot, and gravity.
    let spot = (0..geo.model.mesh.num_nodes())
        .find(|&i| geo.model.posterior[i])
        .unwrap();
    let c = geo.model.mesh.nodes()[spot];
    let text = format!(
        r#"{{"format": 1, "effects": [
            {{"kind": "fixation", "parameters": {{"center": [{}, {}, {}], "radius_mm": 30, "stiffness": 5}}}},
            {{"kind": "gravity", "parameters": {{"direction": [0, 1, 0], "magnitude": 0.0104}}}}]}}"#,
        c[0], c[1], c[2]
    );
    let path = folder.path().join("held.physics.json");
    std::fs::write(&path, &text).unwrap();
    let physics = Physics::read(&path).unwrap();
    let mut running = librplus_server::start(ServerConfig {
        cases: vec![folder.path().to_path_buf()],
        ..config(2)
    })
    .await
    .unwrap();
    running.ready().await.unwrap();
    let mut client = client(running.addr).await;
    let list = client
        .list_cases(pb::ListCasesRequest {})
        .await
        .unwrap()
        .into_inner();
    assert_eq!(list.cases.len(), 1);
    assert_eq!(list.cases[0].effects, ["fixation", "gravity"]);
    let (_, sc) = scenario("surface+2us");
    let lib_case = Prepared::with_physics(
        geo.model.clone(),
        Some(&LibrParams::default()),
        &physics,
        None,
    )
    .unwrap();
    // The held flag (RegisterOptions.held) reaches the pipeline as PipelineParams::held.
    for (trusted, held) in [(0.0, false), (3.0, false), (0.0, true)] {
        let mut req = request("held", pb::Method::Libr, measurements_pb(&sc.measurements));
        req.options = Some(pb::RegisterOptions {
            trusted_alignment_mm: trusted,
            held,
            ..Default::default()
        });
        let r = client.register(req).await.unwrap().into_inner();
        let mut params = PipelineParams::default();
        params.wicp.trusted_alignment_mm = (trusted > 0.0).then_some(trusted);
        params.held = held;
        let lib = register(&lib_case, &sc.measurements, Method::Libr, &params).unwrap();
        assert_eq!(lib.libr.as_ref().unwrap().held_nodes > 0, held);
        // The fixation holds the organ: the start is trusted (5 mm, or as sent).
        assert_eq!(
            lib.rigid.prior.map(|p| p.sigma_mm),
            Some(if trusted > 0.0 { trusted } else { 5.0 })
        );
        let (dt, du) = difference(&r, &lib);
        eprintln!(
            "with physics, trusted {trusted} mm, held {held}: |Δtransform| {dt:.1e}, |Δu| {du:.1e} mm"
        );
        assert_eq!(r.effects, ["fixation", "gravity"]);
        assert!(dt < 1e-9, "transform differs by {dt}");
        assert!(du <= 1e-5, "displacements differ by {du} mm");
        assert!(
            lib.u.iter().any(|&x| x.abs() > 0.5),
            "LIBR deformed nothing"
        );
    }
    let mut bad = request("held", pb::Method::Libr, measurements_pb(&sc.measurements));
    bad.options = Some(pb::RegisterOptions {
        trusted_alignment_mm: -1.0,
        ..Default::default()
    });
    let e = client.register(bad).await.unwrap_err();
    assert_eq!(e.code(), Code::InvalidArgument);
    assert!(
        violations(&e)
            .iter()
            .any(|v| v.contains("options.trusted_alignment_mm")),
        "{e:?}"
    );
    assert_eq!(running.shutdown().await, 0);
}

/// METHOD_ADAPTIVE: refused (FAILED_PRECONDITION naming `method`) by a server that did not
/// prepare adaptive LIBR's basis; answered, as the library answers it, by one started with
/// `adaptive` (the same multi-level basis and fit, to f32 rounding).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn adaptive_libr_is_answered_when_the_server_prepares_it() {
    use librplus::register::libr::AdaptiveParams;
    let (geo, sc) = scenario("surface+2us");
    let m = open(dataset()).unwrap();
    let case = m.deformations[0].geometry.clone();
    let req = || {
        request(
            &case,
            pb::Method::Adaptive,
            measurements_pb(&sc.measurements),
        )
    };
    for adaptive in [false, true] {
        let mut running = librplus_server::start(ServerConfig {
            adaptive,
            ..config(2)
        })
        .await
        .unwrap();
        running.ready().await.unwrap();
        let mut client = client(running.addr).await;
        if !adaptive {
            let e = client.register(req()).await.unwrap_err();
            assert_eq!(e.code(), Code::FailedPrecondition, "{e:?}");
            assert!(e.message().contains("method"), "{}", e.message());
            continue;
        }
        let r = client.register(req()).await.unwrap().into_inner();
        assert_eq!(r.method_used, pb::Method::Adaptive as i32);
        let lib_case = Prepared::new(geo.model.clone(), Some(&LibrParams::default()), None)
            .unwrap()
            .with_adaptive(&LibrParams::default(), &AdaptiveParams::default(), None)
            .unwrap();
        let lib = register(
            &lib_case,
            &sc.measurements,
            Method::Adaptive,
            &PipelineParams::default(),
        )
        .unwrap();
        let (dt, du) = difference(&r, &lib);
        eprintln!("adaptive over the API: |Δtransform| {dt:.1e}, |Δu| {du:.1e} mm");
        assert!(dt < 1e-9, "transform differs by {dt}");
        assert!(du <= 1e-5, "displacements differ by {du} mm");
    }
}

/// METHOD_AUTO: answered by a server that prepared adaptive LIBR's basis as the library answers
/// it (the same candidate chosen, the same displacement to f32 rounding, the same quality flag),
/// the choice named in the answer (chosen, runner-up, every candidate's held-out score) and the
/// side test's outcome, both as the library's and kept in the audit log.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn auto_is_answered_with_its_choice_and_audited() {
    use librplus::register::libr::AdaptiveParams;
    let (geo, sc) = scenario("surface+2us");
    let m = open(dataset()).unwrap();
    let case = m.deformations[0].geometry.clone();
    let dir = tempfile::tempdir().unwrap();
    let db = dir.path().join("audit.db");
    let mut running = librplus_server::start(ServerConfig {
        adaptive: true,
        audit_db: Some(db.clone()),
        // Results independent of timing: the plan never degrades auto to LIBR here.
        time_budget_ms: 60_000,
        ..config(2)
    })
    .await
    .unwrap();
    running.ready().await.unwrap();
    let mut client = client(running.addr).await;
    let req = request(&case, pb::Method::Auto, measurements_pb(&sc.measurements));
    let r = client.register(req).await.unwrap().into_inner();
    running.shutdown().await;
    assert_eq!(r.method_used, pb::Method::Auto as i32);
    let choice = r.choice.as_ref().expect("auto names its choice");
    let lib_case = Prepared::new(geo.model.clone(), Some(&LibrParams::default()), None)
        .unwrap()
        .with_adaptive(&LibrParams::default(), &AdaptiveParams::default(), None)
        .unwrap()
        .with_error_model(librplus::register::uncertainty::builtin());
    let params = PipelineParams::default();
    let lib = register(&lib_case, &sc.measurements, Method::Auto, &params).unwrap();
    let a = lib.auto.as_ref().unwrap();
    eprintln!(
        "auto over the API: chose {} (runner-up {}, margin {:.2} mm², {:.1} SE), quality {:?}",
        choice.chosen,
        choice.runner_up,
        choice.margin_mm2,
        choice.margin_se,
        r.quality()
    );
    assert_eq!(choice.chosen, a.chosen.name());
    assert_eq!(
        choice.runner_up,
        a.runner_up.map_or(String::new(), |c| c.name().to_string())
    );
    // Every candidate tried: doing nothing, rigid, LIBR, adaptive LIBR and (no trusted start:
    // the hold as a hypothesis, ranked after the free fits) their held variants, each scored.
    let names: Vec<&str> = choice.candidates.iter().map(|c| c.name.as_str()).collect();
    assert_eq!(
        names,
        [
            "initial",
            "rigid",
            "libr",
            "adaptive",
            "libr-held",
            "adaptive-held"
        ]
    );
    assert!(
        choice
            .candidates
            .iter()
            .all(|c| c.held_out_mm2.is_some_and(|s| s >= 0.0) && c.failed.is_empty()),
        "{choice:?}"
    );
    let (dt, du) = difference(&r, &lib);
    assert!(
        dt < 1e-9 && du <= 1e-5,
        "transform {dt}, displacement {du} mm"
    );
    let side = lib.surface.as_ref().expect("the side test ran");
    let wire = r.surface.as_ref().expect("the answer names the side");
    assert_eq!(
        (wire.target.as_str(), wire.anterior_mm2, wire.boundary_mm2),
        (side.target.name(), side.anterior_mm2, side.boundary_mm2)
    );
    let judged = lib.quality(&params);
    assert_eq!(
        (r.quality().as_str_name(), r.quality_reason.as_str()),
        (
            librplus_server::compute::quality_to_pb(judged.quality).as_str_name(),
            judged.reason.as_str()
        )
    );
    // The audit log keeps the choice.
    let conn = librplus_server::audit::open_db(&db).unwrap();
    let rows = librplus_server::audit::rows(&conn, None, None).unwrap();
    let reg = rows.iter().find(|r| r.kind == "registration").unwrap();
    assert_eq!(reg.detail["method"], "METHOD_AUTO");
    assert_eq!(reg.detail["choice"]["chosen"], choice.chosen.as_str());
    assert_eq!(
        reg.detail["choice"]["candidates"].as_array().map(Vec::len),
        Some(6)
    );
    assert_eq!(reg.detail["surface"]["target"], wire.target.as_str());
    // Read back from the log's JSON (serde_json's parser may be one ulp off the written value).
    let logged = reg.detail["surface"]["anterior_mm2"].as_f64().unwrap();
    assert!(
        (logged - wire.anterior_mm2).abs() <= 1e-12 * wire.anterior_mm2.abs(),
        "{logged} logged, {} answered",
        wire.anterior_mm2
    );
}

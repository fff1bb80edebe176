//! Unary `Register` over loopback equals the library called directly, for LIBR, LIBR+ and V2S.

use crate::common::*;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn unary_register_equals_the_library() {
    let (running, mut c) = server(4).await;
    let cases = c
        .list_cases(pb::ListCasesRequest {})
        .await
        .unwrap()
        .into_inner();
    assert_eq!(cases.cases.len(), 2, "{cases:?}");
    assert!(
        cases
            .cases
            .iter()
            .all(|s| s.libr_ready && s.basis_from_cache)
    );
    let (geo, sc) = scenario("surface+2us");
    let case = open(dataset()).unwrap().deformations[0].geometry.clone();
    let desc = c
        .describe_case(pb::DescribeCaseRequest {
            case_id: case.clone(),
            include_mesh: true,
        })
        .await
        .unwrap()
        .into_inner();
    assert_eq!(desc.nodes_mm.len(), 3 * geo.model.mesh.num_nodes());
    assert_eq!(desc.tets.len(), 4 * geo.model.mesh.num_tets());
    let anterior = desc.node_labels.iter().filter(|&&l| l & 1 != 0).count();
    assert_eq!(anterior, geo.model.anterior.iter().filter(|&&a| a).count());
    for (method, pm) in [
        (Method::Rigid, pb::Method::Rigid),
        (Method::Libr, pb::Method::Libr),
    ] {
        let r = c
            .register(request(&case, pm, measurements_pb(&sc.measurements)))
            .await
            .unwrap()
            .into_inner();
        let lib = direct(&geo, &sc.measurements, method);
        let (dt, du) = difference(&r, &lib);
        eprintln!(
            "unary {method:?}: quality {:?} ({}), |Δtransform| {dt:.1e}, |Δu| {du:.1e} mm, {:.0} ms",
            r.quality(),
            r.quality_reason,
            r.timings.as_ref().unwrap().total_ms
        );
        assert_eq!(r.method_used, pm as i32);
        assert_ne!(r.quality(), pb::Quality::Degraded);
        assert!(dt < 1e-9, "transform differs by {dt}");
        // f32 on the wire: displacements of tens of mm round at ~1e-6 relative.
        assert!(du < 1e-4, "displacements differ by {du} mm");
        if method == Method::Libr {
            assert!(
                lib.u.iter().any(|&x| x.abs() > 0.5),
                "LIBR deformed nothing"
            );
        }
        // The error estimate: the built-in model's, as the library computes it.
        let (e, want) = (
            r.error_estimate.as_ref().expect("an error estimate"),
            lib.error.as_ref().expect("the library's estimate"),
        );
        assert_eq!(e.node_uncertainty_mm.len(), geo.model.mesh.num_nodes());
        assert!(e.predicted_tre_mm > 0.0 && (e.level - 0.9).abs() < 1e-12);
        // The features read the answer the wire rounds to f32 (|Δu| < 1e-4 mm).
        assert!(
            (e.predicted_tre_mm - want.predicted_tre_mm).abs() < 1e-3 * want.predicted_tre_mm,
            "predicted TRE {} vs the library's {}",
            e.predicted_tre_mm,
            want.predicted_tre_mm
        );
        let worst = e
            .node_uncertainty_mm
            .iter()
            .zip(&want.node_bound_mm)
            .map(|(&a, &b)| (f64::from(a) - b).abs() / b.max(1.0))
            .fold(0.0, f64::max);
        assert!(worst < 1e-3, "node bounds differ by {worst} (relative)");
        // The failure probability: on the wire when the library has one, equal to it.
        match (&e.failure, want.failure_probability) {
            (Some(f), Some(p)) => {
                assert!((f.probability - p).abs() < 1e-3, "{} vs {p}", f.probability);
                assert_eq!(Some(f.threshold_mm), want.failure_threshold_mm);
            }
            (None, None) => {}
            (got, p) => panic!("failure estimate {got:?} on the wire, {p:?} in the library"),
        }
        eprintln!(
            "unary {method:?}: predicted TRE {:.2} mm, mean node bound {:.2} mm",
            e.predicted_tre_mm,
            want.node_bound_mm.iter().sum::<f64>() / want.node_bound_mm.len() as f64
        );
    }
    assert_eq!(running.shutdown().await, 0);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn librplus_answers_through_the_same_api_as_the_library() {
    use librplus::gcn::io::{TrainedModel, save_model};
    use librplus::gcn::model::SrGcnConfig;
    let tmp = tempfile::tempdir().unwrap();
    let cfg = SrGcnConfig::new()
        .with_width(8)
        .with_convs(1)
        .with_levels(2);
    let model = TrainedModel::untrained(cfg, 7).unwrap();
    save_model(
        tmp.path(),
        &model.config,
        &model.net,
        model.provenance.clone(),
    )
    .unwrap();
    let mut running = librplus_server::start(ServerConfig {
        model: Some(tmp.path().to_path_buf()),
        librplus: true,
        ..config(2)
    })
    .await
    .unwrap();
    running.ready().await.unwrap();
    let mut c = client(running.addr).await;
    let cases = c
        .list_cases(pb::ListCasesRequest {})
        .await
        .unwrap()
        .into_inner();
    assert!(cases.cases.iter().all(|s| s.libr_plus_ready), "{cases:?}");
    let (geo, sc) = scenario("surface+1us");
    let case = open(dataset()).unwrap().deformations[0].geometry.clone();
    let r = c
        .register(request(
            &case,
            pb::Method::LibrPlus,
            measurements_pb(&sc.measurements),
        ))
        .await
        .unwrap()
        .into_inner();
    assert_eq!(r.method_used, pb::Method::LibrPlus as i32, "{r:?}");
    assert_ne!(r.quality(), pb::Quality::Degraded, "{}", r.quality_reason);
    let t = r.timings.as_ref().unwrap();
    assert!(
        t.gcn_ms > 0.0 && t.refit_ms > 0.0 && t.refit_ms < t.gcn_ms,
        "{t:?}"
    );
    assert!(t.refit_iterations >= 1, "{t:?}");
    let prepared = Prepared::new(
        geo.model.clone(),
        Some(&LibrParams::default()),
        Some(&dataset().join("cache")),
    )
    .unwrap()
    .with_model(std::sync::Arc::new(
        librplus::gcn::io::load_model_on_device(tmp.path()).unwrap(),
    ))
    .unwrap();
    let p = PipelineParams::default();
    let lib = register(&prepared, &sc.measurements, Method::LibrPlus, &p).unwrap();
    let (dt, du) = difference(&r, &lib);
    assert!(
        dt < 1e-9 && du < 1e-4,
        "transform {dt}, displacements {du} mm"
    );
    // The fit figures are the refit's, the answer's last stage.
    let refit = lib.correction.as_ref().unwrap().refit.as_ref().unwrap();
    assert_eq!(t.refit_iterations as usize, refit.iterations);
    assert!((r.residual_rms_mm - refit.rms_mm).abs() < 1e-6, "{r:?}");
    let libr = register(&prepared, &sc.measurements, Method::Libr, &p).unwrap();
    assert_ne!(lib.u, libr.u);
    assert_eq!(running.shutdown().await, 0);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn v2s_answers_through_the_same_api_as_the_library() {
    use librplus::v2s::io::{V2sModel, save_model};
    use librplus::v2s::model::V2sConfig;
    let tmp = tempfile::tempdir().unwrap();
    let cfg = V2sConfig::new().with_grid(16).with_width(4).with_depth(2);
    let mut model = V2sModel::untrained(cfg, 7).unwrap();
    // A non-zero head, so the answer is not the rigid one.
    let device = burn::tensor::Device::flex();
    device.seed(3);
    let dims = model.net.head.weight.dims();
    model.net.head.weight = burn::module::Param::from_tensor(burn::tensor::Tensor::<5>::random(
        dims,
        burn::tensor::Distribution::Normal(0.0, 0.1),
        &device,
    ));
    save_model(
        tmp.path(),
        &model.config,
        &model.net,
        model.provenance.clone(),
    )
    .unwrap();
    let mut running = librplus_server::start(ServerConfig {
        v2s_model: Some(tmp.path().to_path_buf()),
        v2s: true,
        ..config(2)
    })
    .await
    .unwrap();
    running.ready().await.unwrap();
    let mut c = client(running.addr).await;
    let cases = c
        .list_cases(pb::ListCasesRequest {})
        .await
        .unwrap()
        .into_inner();
    assert!(cases.cases.iter().all(|s| s.v2s_ready), "{cases:?}");
    let (geo, sc) = scenario("surface+1us");
    let case = open(dataset()).unwrap().deformations[0].geometry.clone();
    let r = c
        .register(request(
            &case,
            pb::Method::V2s,
            measurements_pb(&sc.measurements),
        ))
        .await
        .unwrap()
        .into_inner();
    assert_eq!(r.method_used, pb::Method::V2s as i32, "{r:?}");
    let prepared = Prepared::new(geo.model.clone(), None, None)
        .unwrap()
        .with_v2s(std::sync::Arc::new(
            librplus::v2s::io::load_model_on_device(tmp.path()).unwrap(),
        ))
        .unwrap();
    let p = PipelineParams::default();
    let lib = register(&prepared, &sc.measurements, Method::V2s, &p).unwrap();
    let (dt, du) = difference(&r, &lib);
    assert!(
        dt < 1e-9 && du < 1e-4,
        "transform {dt}, displacements {du} mm"
    );
    let rigid = register(&prepared, &sc.measurements, Method::Rigid, &p).unwrap();
    assert_eq!(rigid.image_to_physical, lib.image_to_physical);
    assert!(
        lib.u.iter().any(|x| x.abs() > 1e-3),
        "V2S answered no displacement"
    );
    assert_eq!(running.shutdown().await, 0);
}

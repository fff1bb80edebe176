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
    let mut meas = sc.measurements.clone();
    let keep: Vec<usize> = (0..meas.points.len())
        .filter(|&i| meas.kind[i] != MeasuredKind::Vessel)
        .collect();
    meas.points = keep.iter().map(|&i| meas.points[i]).collect();
    meas.kind = keep.iter().map(|&i| meas.kind[i]).collect();
    meas.feature = keep.iter().map(|&i| meas.feature[i]).collect();
    let r = c
        .register(request("bare", pb::Method::Libr, measurements_pb(&meas)))
        .await
        .unwrap()
        .into_inner();
    assert_eq!(r.method_used(), pb::Method::Libr);
    assert_eq!(r.node_count as usize, geo.model.mesh.num_nodes());
    assert_eq!(running.shutdown().await, 0);
}

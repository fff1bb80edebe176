//! TLS and mTLS, with certificates made here (`rcgen`): a CA, a server certificate for
//! `localhost`, a client certificate it signed, and a client certificate of another CA.

use crate::common::*;

/// ListCases over a client with these TLS settings: Ok(number of cases) or the error in words.
async fn list(url: &str, tls: &librplus_client::Tls) -> Result<usize, String> {
    let mut c = librplus_client::connect_with(url, tls)
        .await
        .map_err(|e| format!("{e:#}"))?;
    c.list_cases(pb::ListCasesRequest {})
        .await
        .map(|r| r.into_inner().cases.len())
        .map_err(|s| format!("{}: {}", s.code(), s.message()))
}

/// A TLS server answers a client that trusts its CA, and not a plaintext client nor one that
/// trusts another CA; with `client_ca` (mTLS) it also refuses a client without a certificate
/// or with one of another CA, and answers one whose certificate its CA signed. Bad settings are
/// refused naming the option.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn tls_and_mutual_tls() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let (ca_pem, ca_issuer) = ca("LIBR+ test CA");
    let (other_pem, other_issuer) = ca("another CA");
    let (server_cert, server_key) = leaf(&["localhost"], &ca_issuer);
    let (client_cert, client_key) = leaf(&["navigation-system-1"], &ca_issuer);
    let (stranger_cert, stranger_key) = leaf(&["stranger"], &other_issuer);
    let ca_file = write(d, "ca.pem", &ca_pem);
    let other_file = write(d, "other.pem", &other_pem);
    let server_cert = write(d, "server.pem", &server_cert);
    let server_key = write(d, "server.key", &server_key);
    let client = (
        write(d, "client.pem", &client_cert),
        write(d, "client.key", &client_key),
    );
    let stranger = (
        write(d, "stranger.pem", &stranger_cert),
        write(d, "stranger.key", &stranger_key),
    );
    let trusting = |ca: &Path, id: Option<&(PathBuf, PathBuf)>| librplus_client::Tls {
        ca: Some(ca.to_path_buf()),
        cert: id.map(|i| i.0.clone()),
        key: id.map(|i| i.1.clone()),
        domain: Some("localhost".into()),
    };
    // TLS.
    let mut running = librplus_server::start(ServerConfig {
        tls_cert: Some(server_cert.clone()),
        tls_key: Some(server_key.clone()),
        ..config(2)
    })
    .await
    .unwrap();
    running.ready().await.unwrap();
    let url = format!("http://{}", running.addr);
    assert_eq!(list(&url, &trusting(&ca_file, None)).await, Ok(2));
    let plain = list(&url, &librplus_client::Tls::default()).await;
    eprintln!("plaintext client against TLS: {plain:?}");
    assert!(plain.is_err());
    let wrong_ca = list(&url, &trusting(&other_file, None)).await;
    eprintln!("client trusting another CA: {wrong_ca:?}");
    assert!(wrong_ca.is_err());
    assert_eq!(running.shutdown().await, 0);
    // mTLS.
    let mut running = librplus_server::start(ServerConfig {
        tls_cert: Some(server_cert.clone()),
        tls_key: Some(server_key.clone()),
        client_ca: Some(ca_file.clone()),
        ..config(2)
    })
    .await
    .unwrap();
    running.ready().await.unwrap();
    let url = format!("http://{}", running.addr);
    assert_eq!(list(&url, &trusting(&ca_file, Some(&client))).await, Ok(2));
    let anonymous = list(&url, &trusting(&ca_file, None)).await;
    eprintln!("mTLS, no client certificate: {anonymous:?}");
    assert!(anonymous.is_err());
    let foreign = list(&url, &trusting(&ca_file, Some(&stranger))).await;
    eprintln!("mTLS, certificate of another CA: {foreign:?}");
    assert!(foreign.is_err());
    // Certificates of the right CA outside their validity.
    for (what, from, to) in [
        ("expired", (2020, 1, 1), (2021, 1, 1)),
        ("not yet valid", (2099, 1, 1), (2100, 1, 1)),
    ] {
        let (cert, key) = leaf_valid(&["navigation-system-1"], &ca_issuer, from, to);
        let id = (
            write(d, &format!("{what}.pem"), &cert),
            write(d, &format!("{what}.key"), &key),
        );
        let r = list(&url, &trusting(&ca_file, Some(&id))).await;
        eprintln!("mTLS, {what} client certificate: {r:?}");
        assert!(r.is_err(), "{what}");
    }
    assert_eq!(running.shutdown().await, 0);
    // Refused settings name the option.
    let half = ServerConfig {
        tls_cert: Some(server_cert.clone()),
        ..config(2)
    };
    let e = librplus_server::start(half)
        .await
        .err()
        .unwrap()
        .to_string();
    assert!(e.contains("tls_key"), "{e}");
    let missing = ServerConfig {
        tls_cert: Some(d.join("nowhere.pem")),
        tls_key: Some(server_key),
        ..config(2)
    };
    let e = format!("{:#}", librplus_server::start(missing).await.err().unwrap());
    assert!(e.contains("--tls-cert") && e.contains("nowhere.pem"), "{e}");
    let e = list(
        &url,
        &librplus_client::Tls {
            cert: Some(client.0.clone()),
            ..trusting(&ca_file, None)
        },
    )
    .await
    .unwrap_err();
    assert!(e.contains("--key"), "{e}");
}

/// A certificate reload (SIGHUP's `reload_tls`) serves new connections with the new files while
/// a session opened before it goes on over its old connection; a reload of unreadable files
/// changes nothing.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn certificates_reload_without_dropping_sessions() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let (ca1_pem, ca1) = ca("first CA");
    let (ca2_pem, ca2) = ca("second CA");
    let ca1_file = write(d, "ca1.pem", &ca1_pem);
    let ca2_file = write(d, "ca2.pem", &ca2_pem);
    let (cert, key) = leaf(&["localhost"], &ca1);
    let cert_file = write(d, "server.pem", &cert);
    let key_file = write(d, "server.key", &key);
    let mut running = librplus_server::start(ServerConfig {
        tls_cert: Some(cert_file.clone()),
        tls_key: Some(key_file.clone()),
        ..config(2)
    })
    .await
    .unwrap();
    running.ready().await.unwrap();
    let url = format!("http://{}", running.addr);
    let trusting = |ca: &Path| librplus_client::Tls {
        ca: Some(ca.to_path_buf()),
        domain: Some("localhost".into()),
        ..Default::default()
    };
    // A session opened under the first certificate.
    let mut c = librplus_client::connect_with(&url, &trusting(&ca1_file))
        .await
        .unwrap();
    let (_, sc) = scenario("surface+2us");
    let g = &open(dataset()).unwrap().geometries[0].id;
    let (msgs, _) = stream_of(g, &sc, pb::Method::Libr);
    let mut s = open_stream(&mut c, msgs[0].clone()).await.unwrap();
    let u = s.send(msgs[1].clone()).await.unwrap();
    assert!(matches!(
        u.update,
        Some(pb::stream_update::Update::Registration(_))
    ));
    // Unreadable files: refused, nothing changes.
    std::fs::write(&cert_file, "not a certificate").unwrap();
    let e = running.reload_tls().await.unwrap_err();
    eprintln!("reload of a bad file: {e:#}");
    assert!(format!("{e:#}").contains("--tls-cert"), "{e:#}");
    assert_eq!(
        list(&url, &trusting(&ca1_file)).await,
        Ok(2),
        "still the first certificate"
    );
    let (cert2, key2) = leaf(&["localhost"], &ca2);
    std::fs::write(&cert_file, &cert2).unwrap();
    std::fs::write(&key_file, &key2).unwrap();
    running.reload_tls().await.unwrap();
    assert_eq!(list(&url, &trusting(&ca2_file)).await, Ok(2));
    let old_ca = list(&url, &trusting(&ca1_file)).await;
    eprintln!("new connection trusting only the first CA: {old_ca:?}");
    assert!(old_ca.is_err());
    // The session opened before the reload goes on.
    let u = s.send(msgs[2].clone()).await.unwrap();
    assert!(
        matches!(u.update, Some(pb::stream_update::Update::Registration(_))),
        "{u:?}"
    );
    drop(s);
    assert_eq!(running.shutdown().await, 0);
}

/// Without client authentication the server listens on loopback only, unless told `insecure`.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_reachable_address_needs_insecure() {
    let e = librplus_server::start(ServerConfig {
        listen: "0.0.0.0:0".into(),
        ..config(2)
    })
    .await
    .err()
    .unwrap()
    .to_string();
    assert!(
        e.contains("--insecure") && e.contains("listen 0.0.0.0:0"),
        "{e}"
    );
    let mut running = librplus_server::start(ServerConfig {
        listen: "0.0.0.0:0".into(),
        insecure: true,
        ..config(2)
    })
    .await
    .unwrap();
    running.ready().await.unwrap();
    assert_eq!(running.shutdown().await, 0);
}

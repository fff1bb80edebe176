//! TLS and mTLS, with certificates made here (`rcgen`): a CA, a server certificate for
//! `localhost`, a client certificate it signed, and a client certificate of another CA.

use crate::common::*;
use rcgen::{BasicConstraints, CertificateParams, DnType, IsCa, Issuer, KeyPair};

/// A CA: its certificate (PEM) and its issuer.
fn ca(name: &str) -> (String, Issuer<'static, KeyPair>) {
    let key = KeyPair::generate().unwrap();
    let mut params = CertificateParams::new(Vec::<String>::new()).unwrap();
    params.is_ca = IsCa::Ca(BasicConstraints::Unconstrained);
    params.distinguished_name.push(DnType::CommonName, name);
    let cert = params.self_signed(&key).unwrap();
    (cert.pem(), Issuer::new(params, key))
}

/// A certificate for `names` signed by `issuer`: (certificate PEM, key PEM).
fn leaf(names: &[&str], issuer: &Issuer<'static, KeyPair>) -> (String, String) {
    let key = KeyPair::generate().unwrap();
    let mut params =
        CertificateParams::new(names.iter().map(|s| s.to_string()).collect::<Vec<_>>()).unwrap();
    params.distinguished_name.push(DnType::CommonName, names[0]);
    let cert = params.signed_by(&key, issuer).unwrap();
    (cert.pem(), key.serialize_pem())
}

fn write(dir: &Path, name: &str, text: &str) -> PathBuf {
    let p = dir.join(name);
    std::fs::write(&p, text).unwrap();
    p
}

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

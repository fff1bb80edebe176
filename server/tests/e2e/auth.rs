//! Authentication and authorization (`--auth`): every RPC tried with no credentials, a wrong
//! token, a malformed header, another tenant's token, a read-only token and the right one; the
//! table of what each got is printed. Client-certificate subjects as principals; health and
//! reflection open or closed; quotas per principal; the auth file reloaded.

use crate::common::*;
use librplus_server::auth::{hex, sha256};

/// The dataset's two case ids.
fn ids() -> (String, String) {
    let m = open(dataset()).unwrap();
    (m.geometries[0].id.clone(), m.geometries[1].id.clone())
}

fn principal(name: &str, token: &str, cases: &[&str], roles: &[&str], max: usize) -> String {
    format!(
        r#"{{"principal":"{name}","token_sha256":["{}"],"cases":{},"roles":{},"max_sessions":{max}}}"#,
        hex(&sha256(token.as_bytes())),
        serde_json::to_string(cases).unwrap(),
        serde_json::to_string(roles).unwrap()
    )
}

fn with<T>(msg: T, auth: Option<&str>) -> tonic::Request<T> {
    let mut r = tonic::Request::new(msg);
    if let Some(a) = auth {
        r.metadata_mut().insert("authorization", a.parse().unwrap());
    }
    r
}

/// A stream's outcome: OK when its first update is a registration, else the refusal's code.
async fn stream_code(c: &mut LibRPlusClient<Channel>, auth: Option<&str>, case: &str) -> Code {
    let (_, sc) = scenario("surface");
    let (msgs, _) = stream_of(case, &sc, pb::Method::Rigid);
    let req = with(tokio_stream::iter(msgs[..2].to_vec()), auth);
    match c.stream_register(req).await {
        Err(s) => s.code(),
        Ok(r) => match r.into_inner().message().await {
            Ok(Some(u)) => match u.update {
                Some(pb::stream_update::Update::Registration(_)) => Code::Ok,
                other => panic!("unexpected update {other:?}"),
            },
            Ok(None) => Code::Unknown,
            Err(s) => s.code(),
        },
    }
}

/// The codes of ListCases, DescribeCase, Register and StreamRegister on `case` with `auth`;
/// the cases ListCases showed.
async fn row(
    c: &mut LibRPlusClient<Channel>,
    auth: Option<&str>,
    case: &str,
) -> ([Code; 4], Vec<String>) {
    let (_, sc) = scenario("surface");
    let code = |r: Result<(), tonic::Status>| r.err().map_or(Code::Ok, |s| s.code());
    let mut listed = Vec::new();
    let list = c
        .list_cases(with(pb::ListCasesRequest {}, auth))
        .await
        .map(|r| {
            listed = r
                .into_inner()
                .cases
                .into_iter()
                .map(|c| c.case_id)
                .collect()
        });
    let describe = c
        .describe_case(with(
            pb::DescribeCaseRequest {
                case_id: case.into(),
                include_mesh: false,
            },
            auth,
        ))
        .await
        .map(|_| ());
    let register = c
        .register(with(
            request(case, pb::Method::Rigid, measurements_pb(&sc.measurements)),
            auth,
        ))
        .await
        .map(|_| ());
    let stream = stream_code(c, auth, case).await;
    ([code(list), code(describe), code(register), stream], listed)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn tokens_scope_every_rpc_to_the_principals_cases_and_roles() {
    let (a, b) = ids();
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("auth.json");
    let a_prefix = format!("{a}*");
    let entries = [
        principal("or-a", "token-a", &[&a_prefix], &["register"], 0),
        principal("or-b", "token-b", &[&b], &["register"], 1),
        principal("viewer", "token-v", &["*"], &["read"], 0),
    ];
    std::fs::write(
        &file,
        format!(r#"{{"format":1,"principals":[{}]}}"#, entries.join(",")),
    )
    .unwrap();
    let mut running = librplus_server::start(ServerConfig {
        auth: Some(file.clone()),
        ..config(4)
    })
    .await
    .unwrap();
    running.ready().await.unwrap();
    let mut c = client(running.addr).await;
    use Code::*;
    let ok_a = [Ok, Ok, Ok, Ok];
    let unauth = [Unauthenticated; 4];
    // (what, authorization header, case, codes of the four RPCs, what ListCases shows)
    type Row<'a> = (&'a str, Option<&'a str>, &'a str, [Code; 4], Vec<&'a str>);
    let table: Vec<Row> = vec![
        ("no credentials", None, &a, unauth, vec![]),
        ("wrong token", Some("Bearer token-x"), &a, unauth, vec![]),
        ("malformed header", Some("token-a"), &a, unauth, vec![]),
        (
            "Basic scheme",
            Some("Basic dG9rZW4tYQ=="),
            &a,
            unauth,
            vec![],
        ),
        (
            "other tenant's token",
            Some("Bearer token-b"),
            &a,
            [Ok, NotFound, NotFound, NotFound],
            vec![&b],
        ),
        (
            "read-only token",
            Some("Bearer token-v"),
            &a,
            [Ok, Ok, PermissionDenied, PermissionDenied],
            vec![&a, &b],
        ),
        ("right token", Some("Bearer token-a"), &a, ok_a, vec![&a]),
        (
            "right token, other case",
            Some("Bearer token-a"),
            &b,
            [Ok, NotFound, NotFound, NotFound],
            vec![&a],
        ),
    ];
    eprintln!(
        "{:<26} {:<14} {:<18} {:<18} {:<18} {:<18} listed",
        "credential", "case", "ListCases", "DescribeCase", "Register", "StreamRegister"
    );
    for (what, auth, case, want, listed_want) in table {
        let (got, listed) = row(&mut c, auth, case).await;
        eprintln!(
            "{what:<26} {case:<14} {:<18} {:<18} {:<18} {:<18} {listed:?}",
            format!("{:?}", got[0]),
            format!("{:?}", got[1]),
            format!("{:?}", got[2]),
            format!("{:?}", got[3]),
        );
        assert_eq!(got, want, "{what}");
        assert_eq!(listed, listed_want, "{what}: ListCases");
    }
    // Another tenant's case and a case that does not exist are refused in the same words.
    let describe = |id: &str| {
        with(
            pb::DescribeCaseRequest {
                case_id: id.into(),
                include_mesh: false,
            },
            Some("Bearer token-b"),
        )
    };
    let theirs = c.describe_case(describe(&a)).await.unwrap_err();
    let none = c.describe_case(describe("no-such-case")).await.unwrap_err();
    assert_eq!(
        theirs.message().replace(&a, "ID"),
        none.message().replace("no-such-case", "ID")
    );
    assert!(!none.message().contains(&a), "{}", none.message());
    // A wrong token is not echoed.
    let e = c
        .list_cases(with(pb::ListCasesRequest {}, Some("Bearer secret-guess")))
        .await
        .unwrap_err();
    assert!(!e.message().contains("secret-guess"), "{}", e.message());
    // Health and reflection answer without credentials (open by default).
    let ch = tonic::transport::Endpoint::from_shared(format!("http://{}", running.addr))
        .unwrap()
        .connect()
        .await
        .unwrap();
    let mut health = tonic_health::pb::health_client::HealthClient::new(ch);
    let h = health
        .check(tonic_health::pb::HealthCheckRequest::default())
        .await
        .unwrap()
        .into_inner();
    assert_eq!(
        h.status(),
        tonic_health::pb::health_check_response::ServingStatus::Serving
    );

    // Quotas per principal: or-b may hold one session; a second is refused while or-a's are
    // admitted.
    let (_, sc) = scenario("surface");
    let (msgs_b, _) = stream_of(&b, &sc, pb::Method::Rigid);
    let (tx, rx) = tokio::sync::mpsc::channel(4);
    tx.send(msgs_b[0].clone()).await.unwrap();
    tx.send(msgs_b[1].clone()).await.unwrap();
    let mut held = c
        .stream_register(with(
            tokio_stream::wrappers::ReceiverStream::new(rx),
            Some("Bearer token-b"),
        ))
        .await
        .unwrap()
        .into_inner();
    assert!(held.message().await.unwrap().is_some());
    assert_eq!(
        stream_code(&mut c, Some("Bearer token-b"), &b).await,
        ResourceExhausted
    );
    assert_eq!(stream_code(&mut c, Some("Bearer token-a"), &a).await, Ok);
    drop(tx);
    drop(held);

    // Reload: token-a removed, token-v made a registrar; open sessions keep their principal.
    std::fs::write(
        &file,
        format!(
            r#"{{"format":1,"principals":[{},{}]}}"#,
            entries[1],
            principal("viewer", "token-v", &["*"], &["register"], 0)
        ),
    )
    .unwrap();
    running.reload_auth().unwrap();
    assert_eq!(row(&mut c, Some("Bearer token-a"), &a).await.0, unauth);
    assert_eq!(row(&mut c, Some("Bearer token-v"), &a).await.0, ok_a);
    // A broken file changes nothing.
    std::fs::write(&file, r#"{"format":1,"principals":[{"principal":"x"}]}"#).unwrap();
    let e = running.reload_auth().unwrap_err();
    eprintln!("broken auth file: {e:#}");
    assert_eq!(row(&mut c, Some("Bearer token-v"), &a).await.0, ok_a);
    assert_eq!(running.shutdown().await, 0);
}

/// A stream that never sends its SessionStart holds no session slot and is closed after
/// `session_start_timeout_s` (finding 7.1): with more silent streams than slots, a real session
/// is admitted and answered.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn silent_streams_hold_no_session_slot() {
    let mut running = librplus_server::start(ServerConfig {
        session_start_timeout_s: 1.0,
        ..config(2)
    })
    .await
    .unwrap();
    running.ready().await.unwrap();
    let mut c = client(running.addr).await;
    let mut silent = Vec::new();
    for _ in 0..8 {
        let (tx, rx) = tokio::sync::mpsc::channel::<pb::StreamRegisterRequest>(1);
        let s = c
            .stream_register(tokio_stream::wrappers::ReceiverStream::new(rx))
            .await
            .unwrap()
            .into_inner();
        silent.push((tx, s));
    }
    let (a, _) = ids();
    let t0 = std::time::Instant::now();
    assert_eq!(stream_code(&mut c, None, &a).await, Code::Ok);
    assert_eq!(stream_code(&mut c, None, &a).await, Code::Ok);
    eprintln!(
        "two real sessions beside 8 silent streams (2 slots): answered in {:.2} s",
        t0.elapsed().as_secs_f64()
    );
    // The silent ones end with DEADLINE_EXCEEDED, naming the SessionStart.
    let t0 = std::time::Instant::now();
    for (_tx, mut s) in silent {
        let e = s.message().await.unwrap_err();
        assert_eq!(e.code(), Code::DeadlineExceeded, "{e:?}");
        assert!(e.message().contains("SessionStart"), "{}", e.message());
    }
    assert!(t0.elapsed() < Duration::from_secs(5));
    assert_eq!(running.shutdown().await, 0);
}

/// With mTLS, a client certificate's subject is the principal; the auth file may close health
/// and reflection to callers without credentials; a non-loopback address is allowed with an
/// auth file.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn certificate_subjects_are_principals() {
    let (a, _) = ids();
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let (ca_pem, issuer) = ca("LIBR+ test CA");
    let (server_cert, server_key) = leaf(&["localhost"], &issuer);
    let (nav_cert, nav_key) = leaf(&["navigation-a"], &issuer);
    let (other_cert, other_key) = leaf(&["unlisted-device"], &issuer);
    let ca_file = write(d, "ca.pem", &ca_pem);
    let file = write(
        d,
        "auth.json",
        &format!(
            r#"{{"format":1,"open_health":false,"principals":[
              {{"principal":"nav-a","certificate_subjects":["CN=navigation-a"],"cases":["{a}"],"roles":["register"]}},
              {}]}}"#,
            principal("ops", "token-ops", &["*"], &["read"], 0)
        ),
    );
    let mut running = librplus_server::start(ServerConfig {
        listen: "0.0.0.0:0".into(),
        auth: Some(file),
        tls_cert: Some(write(d, "server.pem", &server_cert)),
        tls_key: Some(write(d, "server.key", &server_key)),
        client_ca: Some(ca_file.clone()),
        ..config(2)
    })
    .await
    .expect("a non-loopback address is allowed with an auth file");
    running.ready().await.unwrap();
    let url = format!("http://127.0.0.1:{}", running.addr.port());
    let tls = |cert: &str, key: &str, name: &str| librplus_client::Tls {
        ca: Some(ca_file.clone()),
        cert: Some(write(d, &format!("{name}.pem"), cert)),
        key: Some(write(d, &format!("{name}.key"), key)),
        domain: Some("localhost".into()),
    };
    let mut nav = librplus_client::connect_with(&url, &tls(&nav_cert, &nav_key, "nav"))
        .await
        .unwrap();
    let listed: Vec<String> = nav
        .list_cases(pb::ListCasesRequest {})
        .await
        .unwrap()
        .into_inner()
        .cases
        .into_iter()
        .map(|c| c.case_id)
        .collect();
    assert_eq!(listed, std::slice::from_ref(&a));
    assert_eq!(stream_code(&mut nav, None, &a).await, Code::Ok);
    let mut other = librplus_client::connect_with(&url, &tls(&other_cert, &other_key, "other"))
        .await
        .unwrap();
    let e = other.list_cases(pb::ListCasesRequest {}).await.unwrap_err();
    eprintln!("certificate not in the auth file: {e:?}");
    assert_eq!(e.code(), Code::Unauthenticated);
    // A token beats the certificate.
    let r = other
        .list_cases(with(pb::ListCasesRequest {}, Some("Bearer token-ops")))
        .await
        .unwrap();
    assert_eq!(r.into_inner().cases.len(), 2);
    // Health closed: only with credentials.
    let ch = tonic::transport::Endpoint::from_shared(url.replace("http://", "https://"))
        .unwrap()
        .tls_config(
            tonic::transport::ClientTlsConfig::new()
                .ca_certificate(tonic::transport::Certificate::from_pem(&ca_pem))
                .identity(tonic::transport::Identity::from_pem(
                    &other_cert,
                    &other_key,
                ))
                .domain_name("localhost"),
        )
        .unwrap()
        .connect()
        .await
        .unwrap();
    let mut health = tonic_health::pb::health_client::HealthClient::new(ch);
    let e = health
        .check(tonic_health::pb::HealthCheckRequest::default())
        .await
        .unwrap_err();
    assert_eq!(e.code(), Code::Unauthenticated);
    health
        .check(with(
            tonic_health::pb::HealthCheckRequest::default(),
            Some("Bearer token-ops"),
        ))
        .await
        .unwrap();
    assert_eq!(running.shutdown().await, 0);
}

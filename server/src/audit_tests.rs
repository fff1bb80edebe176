//! Tests of the audit log (`audit.rs`).

use super::*;

#[test]
fn times_parse_and_print_in_utc() {
    assert_eq!(parse_since("0").unwrap(), 0);
    assert_eq!(parse_since("1970-01-02").unwrap(), 86_400_000);
    // 2026-11-26T17:00:00Z (`date -u -d 2026-11-26T17:00:00 +%s` = 1795712400).
    assert_eq!(
        parse_since("2026-11-26T17:00:00Z").unwrap(),
        1_795_712_400_000
    );
    assert_eq!(format_ms(1_795_712_400_123), "2026-11-26T17:00:00.123Z");
    assert_eq!(format_ms(951_782_400_000), "2000-02-29T00:00:00.000Z");
    assert_eq!(parse_since("2000-02-29T00:00").unwrap(), 951_782_400_000);
    let e = parse_since("yesterday").unwrap_err();
    assert_eq!(e.given, "yesterday");
    assert!(e.to_string().starts_with("--since \"yesterday\": "), "{e}");
    assert!(parse_since("2026-13-01").is_err());
}

#[tokio::test]
async fn records_are_committed_and_read_back() {
    let dir = tempfile::tempdir().unwrap();
    let db = dir.path().join("audit.db");
    let a = Audit::open(&db, None).unwrap();
    a.write(vec![
        Record::SessionStart {
            session_id: "s1".into(),
            principal: "p".into(),
            case_id: "c".into(),
            case_version: "v1".into(),
            start: vec![1, 2, 3],
        },
        Record::Messages {
            session_id: "s1".into(),
            messages: vec![(3, vec![9]), (2, vec![8])],
        },
    ])
    .await
    .unwrap();
    // Concurrent writers are committed together and each told so.
    let mut tasks = Vec::new();
    let a = std::sync::Arc::new(a);
    for i in 0..50u64 {
        let a = a.clone();
        tasks.push(tokio::spawn(async move {
            a.write(vec![Record::Registration(Box::new(RegistrationRecord {
                principal: "p".into(),
                case_id: "c".into(),
                session_id: Some("s1".into()),
                client_seq: i,
                answer_sha256: format!("{i}"),
                ..Default::default()
            }))])
            .await
        }));
    }
    for t in tasks {
        t.await.unwrap().unwrap();
    }
    // Another connection (as `librplus-server audit` or a restarted server) sees it all.
    let c = open_db(&db).unwrap();
    let s = read_session(&c, "s1").unwrap().unwrap();
    assert_eq!((s.principal.as_str(), s.case_id.as_str()), ("p", "c"));
    assert_eq!(s.start, [1, 2, 3]);
    assert_eq!(s.case_version.as_deref(), Some("v1"));
    assert_eq!(s.messages, [(2, vec![8]), (3, vec![9])]);
    // A client_seq again: the same content is kept once, other content is refused.
    let again = |m: Vec<u8>| Record::Messages {
        session_id: "s1".into(),
        messages: vec![(3, m)],
    };
    a.write(vec![again(vec![9])]).await.unwrap();
    let e = a.write(vec![again(vec![7])]).await.unwrap_err();
    assert!(matches!(e, AuditError::Sql { .. }), "{e:?}");
    assert!(
        e.to_string()
            .contains("client_seq 3 is recorded with other content"),
        "{e}"
    );
    let s = read_session(&c, "s1").unwrap().unwrap();
    assert_eq!(s.messages, [(2, vec![8]), (3, vec![9])]);
    let n: i64 = c
        .query_row("SELECT COUNT(*) FROM registrations", [], |r| r.get(0))
        .unwrap();
    assert_eq!(n, 50);
    assert!(read_session(&c, "s2").unwrap().is_none());
    let rows = rows(&c, Some("c"), None).unwrap();
    assert_eq!(rows.iter().filter(|r| r.kind == "registration").count(), 50);
    assert_eq!(rows.iter().filter(|r| r.kind == "session_start").count(), 1);
    // Another format is refused.
    c.execute("UPDATE meta SET value = '9' WHERE key = 'format'", [])
        .unwrap();
    assert!(matches!(open_db(&db), Err(AuditError::Format { .. })));
}

#[test]
fn a_format_1_database_is_migrated_and_its_sessions_have_no_version() {
    let dir = tempfile::tempdir().unwrap();
    let db = dir.path().join("audit.db");
    {
        // The format-1 schema as it was.
        let c = Connection::open(&db).unwrap();
        c.execute_batch(
            "CREATE TABLE meta(key TEXT PRIMARY KEY, value TEXT NOT NULL);
             INSERT INTO meta VALUES('format', '1');
             CREATE TABLE sessions(session_id TEXT PRIMARY KEY, t_ms INTEGER NOT NULL,
               principal TEXT NOT NULL, case_id TEXT NOT NULL, start BLOB NOT NULL,
               ended_ms INTEGER, outcome TEXT);
             INSERT INTO sessions VALUES('s1', 0, 'p', 'c', x'01', NULL, NULL);",
        )
        .unwrap();
    }
    let c = open_db(&db).unwrap();
    let s = read_session(&c, "s1").unwrap().unwrap();
    assert_eq!(s.case_version, None);
    let f: String = c
        .query_row("SELECT value FROM meta WHERE key = 'format'", [], |r| {
            r.get(0)
        })
        .unwrap();
    assert_eq!(f, FORMAT.to_string());
    drop(c);
    // Opened again: nothing more to do.
    open_db(&db).unwrap();
}

#[test]
fn a_format_2_database_gains_the_choice_and_surface_columns_and_keeps_its_registrations() {
    let dir = tempfile::tempdir().unwrap();
    let db = dir.path().join("audit.db");
    {
        // The format-2 registrations table as it was (no choice).
        let c = Connection::open(&db).unwrap();
        c.execute_batch(
            "CREATE TABLE meta(key TEXT PRIMARY KEY, value TEXT NOT NULL);
             INSERT INTO meta VALUES('format', '2');
             CREATE TABLE registrations(id INTEGER PRIMARY KEY, t_ms INTEGER NOT NULL,
               principal TEXT NOT NULL, case_id TEXT NOT NULL, session_id TEXT,
               client_seq INTEGER, method TEXT, quality TEXT, quality_reason TEXT,
               total_ms REAL, residual_rms_mm REAL, points_total INTEGER, measurements BLOB,
               answer_sha256 TEXT NOT NULL, timings TEXT);
             INSERT INTO registrations(t_ms, principal, case_id, answer_sha256)
               VALUES(1, 'p', 'c', 'old');",
        )
        .unwrap();
    }
    let c = open_db(&db).unwrap();
    type Row = (String, Option<String>, Option<String>);
    let choices: Vec<Row> = c
        .prepare("SELECT answer_sha256, choice, surface FROM registrations")
        .unwrap()
        .query_map([], |r| Ok((r.get(0)?, r.get(1)?, r.get(2)?)))
        .unwrap()
        .collect::<Result<_, _>>()
        .unwrap();
    assert_eq!(choices, [("old".to_string(), None, None)]);
    let f: String = c
        .query_row("SELECT value FROM meta WHERE key = 'format'", [], |r| {
            r.get(0)
        })
        .unwrap();
    assert_eq!(f, FORMAT.to_string());
    // A new registration keeps its choice and its side.
    let g = RegistrationRecord {
        principal: "p".into(),
        case_id: "c".into(),
        answer_sha256: "new".into(),
        choice: Some(r#"{"chosen":"libr"}"#.into()),
        surface: Some(r#"{"target":"boundary"}"#.into()),
        ..Default::default()
    };
    write_registration(&c, &g, 2).unwrap();
    let kept: (Option<String>, Option<String>) = c
        .query_row(
            "SELECT choice, surface FROM registrations WHERE answer_sha256 = 'new'",
            [],
            |r| Ok((r.get(0)?, r.get(1)?)),
        )
        .unwrap();
    assert_eq!(kept.0.as_deref(), Some(r#"{"chosen":"libr"}"#));
    assert_eq!(kept.1.as_deref(), Some(r#"{"target":"boundary"}"#));
}

/// A refusal is shown in the table as its text, its quotes as the client's message has them
/// (as JSON, then escaped by the table, they came out `\\"`); other details stay JSON.
#[test]
fn refusals_are_shown_as_their_text() {
    let row = |kind: &str, detail: serde_json::Value| Row {
        t_ms: 0,
        time: format_ms(0),
        kind: kind.into(),
        principal: "p".into(),
        case_id: None,
        session_id: None,
        detail,
    };
    let refused = row(
        "refused",
        serde_json::json!({"rpc": "DescribeCase", "code": "NOT_FOUND", "message": "case_id \"x\": no such case"}),
    );
    assert_eq!(
        refused.detail_text(),
        "DescribeCase NOT_FOUND: case_id \"x\": no such case"
    );
    let stream = row(
        "refused",
        serde_json::json!({"rpc": "StreamRegister", "outcome": "NOT_FOUND: case_id \"x\""}),
    );
    assert_eq!(
        stream.detail_text(),
        "StreamRegister NOT_FOUND: case_id \"x\""
    );
    let other = row("case_created", serde_json::json!({"nodes": 3}));
    assert_eq!(other.detail_text(), r#"{"nodes":3}"#);
}

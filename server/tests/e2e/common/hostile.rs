//! Hostile peers for the adversarial tests: principals in an auth file, bearer tokens, idle
//! HTTP/2 connections from many loopback addresses, trickled uploads.

use super::*;
use librplus_server::auth::{hex, sha256};

/// An auth file of principals (name, token, cases, roles) with no session quota of their own.
pub fn auth_file(dir: &Path, principals: &[(&str, &str, &[&str], &[&str])]) -> PathBuf {
    let entries: Vec<String> = principals
        .iter()
        .map(|(name, token, cases, roles)| {
            format!(
                r#"{{"principal":"{name}","token_sha256":["{}"],"cases":{},"roles":{}}}"#,
                hex(&sha256(token.as_bytes())),
                serde_json::to_string(cases).unwrap(),
                serde_json::to_string(roles).unwrap()
            )
        })
        .collect();
    write(
        dir,
        "auth.json",
        &format!(r#"{{"format":1,"principals":[{}]}}"#, entries.join(",")),
    )
}

/// `msg` with a bearer token.
pub fn bearer<T>(msg: T, token: &str) -> tonic::Request<T> {
    let mut r = tonic::Request::new(msg);
    r.metadata_mut()
        .insert("authorization", format!("Bearer {token}").parse().unwrap());
    r
}

/// An upload that sends its first message, then one byte a second (`seconds` of them).
pub fn trickle(
    id: &str,
    seconds: u64,
) -> impl tokio_stream::Stream<Item = pb::CreateCaseRequest> + use<> {
    use pb::create_case_request::Part;
    let first = pb::CreateCaseRequest {
        part: Some(Part::Upload(pb::CaseUpload {
            case_id: id.into(),
            mesh_format: "vtu".into(),
            total_bytes: 1 << 20,
            ..Default::default()
        })),
    };
    let bytes = (0..seconds).map(|_| pb::CreateCaseRequest {
        part: Some(Part::Chunk(pb::CaseChunk {
            file: pb::CaseFile::Mesh as i32,
            data: vec![b' '],
        })),
    });
    tokio_stream::StreamExt::throttle(
        tokio_stream::iter(std::iter::once(first).chain(bytes)),
        Duration::from_secs(1),
    )
}

/// The dataset's first preoperative mesh as an upload under `id`.
pub fn mesh_upload(id: &str) -> Vec<pb::CreateCaseRequest> {
    let m = open(dataset()).unwrap();
    let bytes = std::fs::read(dataset().join(&m.geometries[0].preop)).unwrap();
    file_upload(id, "vtu", &bytes)
}

/// An upload of a mesh file's `bytes` in `format` under `id`: the CaseUpload, then chunks of
/// 256 KiB.
pub fn file_upload(id: &str, format: &str, bytes: &[u8]) -> Vec<pb::CreateCaseRequest> {
    use pb::create_case_request::Part;
    let mut out = vec![pb::CreateCaseRequest {
        part: Some(Part::Upload(pb::CaseUpload {
            case_id: id.into(),
            mesh_format: format.into(),
            total_bytes: bytes.len() as u64,
            ..Default::default()
        })),
    }];
    for c in bytes.chunks(256 << 10) {
        out.push(pb::CreateCaseRequest {
            part: Some(Part::Chunk(pb::CaseChunk {
                file: pb::CaseFile::Mesh as i32,
                data: c.to_vec(),
            })),
        });
    }
    out
}

/// Bytes of the files under `path`.
pub fn dir_bytes(path: &Path) -> u64 {
    match std::fs::symlink_metadata(path) {
        Ok(m) if m.is_dir() => std::fs::read_dir(path)
            .map(|r| r.flatten().map(|e| dir_bytes(&e.path())).sum())
            .unwrap_or(0),
        Ok(m) => m.len(),
        Err(_) => 0,
    }
}

/// A stream opened with a bearer token, its first message sent.
pub async fn open_stream_as(
    c: &mut LibRPlusClient<Channel>,
    start: pb::StreamRegisterRequest,
    token: &str,
) -> Result<Stream, tonic::Status> {
    let (tx, rx) = tokio::sync::mpsc::channel(16);
    tx.send(start).await.unwrap();
    let resp = c
        .stream_register(bearer(
            tokio_stream::wrappers::ReceiverStream::new(rx),
            token,
        ))
        .await?;
    Ok(Stream {
        tx,
        rx: resp.into_inner(),
    })
}

/// An idle HTTP/2 connection from `local` to `addr`: the client preface and an empty SETTINGS
/// sent, the server's SETTINGS acknowledged and its PINGs answered (as RFC 9113 asks of a
/// peer), no stream ever opened. The task ends when the server closes the connection.
pub async fn idle_h2(
    local: std::net::Ipv4Addr,
    addr: std::net::SocketAddr,
) -> Option<tokio::task::JoinHandle<()>> {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let sock = tokio::net::TcpSocket::new_v4().ok()?;
    sock.bind((local, 0).into()).ok()?;
    let mut tcp = sock.connect(addr).await.ok()?;
    let mut hello = b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n".to_vec();
    hello.extend(h2_frame(0x4, 0, &[]));
    tcp.write_all(&hello).await.ok()?;
    Some(tokio::spawn(async move {
        let mut head = [0u8; 9];
        loop {
            if tcp.read_exact(&mut head).await.is_err() {
                return;
            }
            let len = u32::from_be_bytes([0, head[0], head[1], head[2]]) as usize;
            let (kind, flags) = (head[3], head[4]);
            let mut body = vec![0u8; len];
            if tcp.read_exact(&mut body).await.is_err() {
                return;
            }
            let answer = match (kind, flags & 1) {
                (0x4, 0) => h2_frame(0x4, 1, &[]),   // SETTINGS: ACK
                (0x6, 0) => h2_frame(0x6, 1, &body), // PING: ACK with its payload
                (0x7, _) => return,                  // GOAWAY
                _ => continue,
            };
            if tcp.write_all(&answer).await.is_err() {
                return;
            }
        }
    }))
}

/// An HTTP/2 frame on stream 0: its 9-byte header (length, type, flags) and payload.
fn h2_frame(kind: u8, flags: u8, payload: &[u8]) -> Vec<u8> {
    let n = payload.len() as u32;
    let mut f = n.to_be_bytes()[1..].to_vec();
    f.extend([kind, flags, 0, 0, 0, 0]);
    f.extend_from_slice(payload);
    f
}

/// `n` idle HTTP/2 connections, spread over loopback addresses 127.0.0.2, .3, … (`per` from
/// each); the ones the server took (some may be closed at once).
pub async fn idle_flood(
    addr: std::net::SocketAddr,
    n: usize,
    per: usize,
) -> Vec<tokio::task::JoinHandle<()>> {
    let mut held = Vec::with_capacity(n);
    for k in 0..n {
        let ip = std::net::Ipv4Addr::new(127, 0, 0, 2 + (k / per) as u8);
        if let Some(h) = idle_h2(ip, addr).await {
            held.push(h);
        }
    }
    held
}

/// `n` idle HTTP/2 connections from loopback address `local`; the ones the server took.
pub async fn idle_flood_from(
    addr: std::net::SocketAddr,
    local: std::net::Ipv4Addr,
    n: usize,
) -> Vec<tokio::task::JoinHandle<()>> {
    let mut held = Vec::with_capacity(n);
    for _ in 0..n {
        if let Some(h) = idle_h2(local, addr).await {
            held.push(h);
        }
    }
    held
}

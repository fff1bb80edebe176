//! Streamed sessions: each update equals the library on the points so far, and messages sent faster than answers are folded into the newest state.

use crate::common::*;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn streamed_session_equals_the_library_on_the_points_so_far() {
    let (running, mut c) = server(4).await;
    let (geo, sc) = scenario("surface+1us");
    let case = open(dataset()).unwrap().deformations[0].geometry.clone();
    let (msgs, ordered) = stream_of(&case, &sc, pb::Method::Libr);
    assert!(msgs.len() >= 3);
    let mut msgs = msgs.into_iter();
    let mut s = open_stream(&mut c, msgs.next().unwrap()).await.unwrap();
    let mut last = None;
    let mut seq = 0;
    for m in msgs {
        let cs = m.client_seq;
        let u = s.send(m).await.unwrap();
        seq += 1;
        assert_eq!(u.sequence, seq);
        assert_eq!(u.last_client_seq, cs);
        assert!(u.session_id.starts_with('s'));
        last = Some(u);
    }
    let last = last.unwrap();
    assert_eq!(last.points_total as usize, ordered.points.len());
    let Some(pb::stream_update::Update::Registration(r)) = last.update else {
        panic!("expected a registration, got {:?}", last.update);
    };
    let lib = direct(&geo, &ordered, Method::Libr);
    let (dt, du) = difference(&r, &lib);
    eprintln!(
        "stream: {} updates, final |Δtransform| {dt:.1e}, |Δu| {du:.1e} mm",
        seq
    );
    assert!(dt < 1e-9 && du < 1e-4, "{dt} {du}");
    drop(s);
    assert_eq!(running.shutdown().await, 0);
}

/// A client that sends faster than registrations complete: messages waiting when a registration
/// ends are folded into the next one (latest wins), every update answers the newest message it
/// saw, and the last one registers every point (equal to the library).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn messages_sent_faster_than_answers_are_folded_into_the_newest_state() {
    let (running, mut c) = server(4).await;
    let (geo, sc) = scenario("surface+16us");
    let case = open(dataset()).unwrap().deformations[0].geometry.clone();
    let (msgs, ordered) = stream_of(&case, &sc, pb::Method::Libr);
    let last_seq = msgs.last().unwrap().client_seq;
    let n = msgs.len();
    let (tx, rx) = tokio::sync::mpsc::channel(n);
    for m in msgs {
        tx.send(m).await.unwrap();
    }
    drop(tx);
    let mut updates = c
        .stream_register(tokio_stream::wrappers::ReceiverStream::new(rx))
        .await
        .unwrap()
        .into_inner();
    let mut got = Vec::new();
    while let Some(u) = updates.message().await.unwrap() {
        got.push(u);
    }
    eprintln!("{} messages, {} updates", n - 1, got.len());
    assert!(
        !got.is_empty() && got.len() < n - 1,
        "{} updates for {} messages",
        got.len(),
        n - 1
    );
    assert!(
        got.windows(2)
            .all(|w| w[0].last_client_seq < w[1].last_client_seq)
    );
    let last = got.pop().unwrap();
    assert_eq!(last.last_client_seq, last_seq);
    assert_eq!(last.points_total as usize, ordered.points.len());
    let Some(pb::stream_update::Update::Registration(r)) = last.update else {
        panic!("expected a registration");
    };
    let (dt, du) = difference(&r, &direct(&geo, &ordered, Method::Libr));
    assert!(dt < 1e-9 && du < 1e-4, "{dt} {du}");
    assert_eq!(running.shutdown().await, 0);
}

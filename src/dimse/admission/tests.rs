//! Pending connections: the caps and which connection makes room; the request read ahead.

use super::*;
use dicom_ul::pdu::{AssociationRQ, PresentationContextProposed};
use tokio::net::TcpListener;

fn ip(s: &str) -> IpAddr {
    s.parse().unwrap()
}

#[test]
fn a_newcomer_over_its_address_cap_closes_that_address_oldest_connection() {
    let pending = Arc::new(Pending::new(2, 10));
    let (mut a1, n1) = pending.enter(ip("10.0.0.1"));
    let (mut a2, n2) = pending.enter(ip("::ffff:10.0.0.1"));
    let (mut b1, _) = pending.enter(ip("10.0.0.2"));
    assert_eq!((n1, n2), (0, 0));
    assert_eq!(pending.count(ip("10.0.0.1")), (3, 2));
    let (_a3, n3) = pending.enter(ip("10.0.0.1"));
    assert_eq!(n3, 1);
    assert_eq!(a1.closed.try_recv(), Ok(()));
    assert!(a2.closed.try_recv().is_err());
    assert!(b1.closed.try_recv().is_err());
    assert_eq!(pending.count(ip("10.0.0.1")), (3, 2));
    // A closed connection's ticket, dropped later, frees nothing twice.
    drop(a1);
    assert_eq!(pending.count(ip("10.0.0.1")), (3, 2));
    drop(a2);
    assert_eq!(pending.count(ip("10.0.0.1")), (2, 1));
}

#[test]
fn a_newcomer_over_the_node_cap_closes_the_oldest_connection_of_any_address() {
    let pending = Arc::new(Pending::new(8, 3));
    let mut tickets: Vec<Ticket> = (1..=3)
        .map(|k| pending.enter(ip(&format!("10.0.0.{k}"))).0)
        .collect();
    let (_late, closed) = pending.enter(ip("10.0.0.9"));
    assert_eq!(closed, 1);
    assert_eq!(tickets[0].closed.try_recv(), Ok(()));
    assert!(tickets[1].closed.try_recv().is_err());
    assert_eq!(pending.count(ip("10.0.0.1")), (3, 0));
    tickets.clear();
    assert_eq!(pending.count(ip("10.0.0.9")), (1, 1));
}

#[tokio::test]
async fn a_connection_is_accepted_only_while_pending_ones_hold_at_most_the_cap_of_sockets() {
    let pending = Arc::new(Pending::new(8, 2));
    let (a, _) = pending.enter(ip("10.0.0.1"));
    let (_b, _) = pending.enter(ip("10.0.0.1"));
    let room = || tokio::time::timeout(Duration::from_millis(50), pending.room());
    assert!(room().await.is_ok());
    // The third closes the first, whose task has not yet ended: three sockets for two places.
    let (_c, closed) = pending.enter(ip("10.0.0.2"));
    assert_eq!(closed, 1);
    assert!(room().await.is_err());
    drop(a);
    assert!(room().await.is_ok());
}

#[test]
fn out_of_descriptors_the_oldest_pending_connection_is_closed() {
    let pending = Arc::new(Pending::new(8, 8));
    assert!(!pending.close_oldest());
    let (mut first, _) = pending.enter(ip("10.0.0.1"));
    let (mut second, _) = pending.enter(ip("10.0.0.2"));
    assert!(pending.close_oldest());
    assert_eq!(first.closed.try_recv(), Ok(()));
    assert!(second.closed.try_recv().is_err());
    assert_eq!(pending.count(ip("10.0.0.2")), (1, 1));
}

#[test]
fn a_throttled_event_is_logged_once_per_period_with_its_count() {
    let t = Throttle::new(Duration::from_secs(3600));
    assert_eq!(t.tick(), Some(1));
    assert_eq!(t.tick(), None);
    assert_eq!(t.tick(), None);
    let t = Throttle::new(Duration::ZERO);
    assert_eq!((t.tick(), t.tick()), (Some(1), Some(1)));
}

fn request(calling: &str, contexts: usize) -> Vec<u8> {
    encode(&Pdu::AssociationRQ(AssociationRQ {
        protocol_version: 1,
        calling_ae_title: calling.into(),
        called_ae_title: "CTRECON".into(),
        application_context_name: "1.2.840.10008.3.1.1.1".into(),
        presentation_contexts: (0..contexts)
            .map(|k| PresentationContextProposed {
                id: (2 * k + 1) as u8,
                abstract_syntax: "1.2.840.10008.5.1.4.1.1.2".into(),
                transfer_syntaxes: vec!["1.2.840.10008.1.2.1".into()],
            })
            .collect(),
        user_variables: vec![],
    }))
}

/// The opening the node reads from a caller that sends `pieces` with `gap` between them.
async fn opening_of(pieces: Vec<Vec<u8>>, gap: Duration) -> (Opening, usize) {
    let listener = TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = listener.local_addr().unwrap();
    let caller = tokio::spawn(async move {
        let mut s = TcpStream::connect(addr).await.unwrap();
        // A caller that sends nothing closes at once; the others stay connected.
        let close = pieces.is_empty();
        for p in pieces {
            s.write_all(&p).await.unwrap();
            tokio::time::sleep(gap).await;
        }
        (!close).then_some(s)
    });
    let (socket, _) = listener.accept().await.unwrap();
    let got = tokio::time::timeout(Duration::from_secs(5), read_opening(&socket))
        .await
        .unwrap();
    let _caller = caller.await.unwrap();
    // Every byte is still there for the negotiation.
    let mut buf = vec![0u8; MAX_REQUEST_BYTES];
    let unread = socket.try_read(&mut buf).unwrap_or(0);
    (got, unread)
}

#[tokio::test]
async fn a_request_in_pieces_is_read_whole_and_left_on_the_socket() {
    let rq = request("PEER", 100);
    assert!(rq.len() > 6000, "{}", rq.len());
    let pieces = vec![rq[..3].to_vec(), rq[3..4000].to_vec(), rq[4000..].to_vec()];
    let (got, unread) = opening_of(pieces, Duration::from_millis(30)).await;
    let want = Opening::Request {
        called: "CTRECON".into(),
        calling: "PEER".into(),
        len: rq.len(),
    };
    assert_eq!((got, unread), (want, rq.len()));
}

#[tokio::test]
async fn other_bytes_oversized_requests_and_closed_sockets_are_no_request() {
    let http = b"GET / HTTP/1.1\r\n\r\n".to_vec();
    let huge = vec![0x01, 0, 0x40, 0, 0, 0, 0, 1];
    let mut short = request("PEER", 1);
    short.truncate(HEADER + 20);
    short[2..6].copy_from_slice(&20u32.to_be_bytes());
    let mut broken = request("PEER", 1);
    broken[HEADER + FIXED + 2] = 0x7F; // the first item's length overruns the PDU
    for bytes in [http, huge, short, broken] {
        let (got, _) = opening_of(vec![bytes.clone()], Duration::ZERO).await;
        assert!(matches!(got, Opening::NotARequest(_)), "{bytes:?}: {got:?}");
    }
    let (got, _) = opening_of(vec![], Duration::ZERO).await;
    assert_eq!(got, Opening::Closed);
}

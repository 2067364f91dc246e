// Included with `include!` by the test helpers that hand a port to a peer process (Orthanc, PostgreSQL,
// s3s-fs, chromedriver, a DICOM node): one way of picking it everywhere.

/// A port nothing listens on at `host`, picked below Linux's ephemeral range (32768–60999): a port the
/// kernel hands out for `bind(0)` can be taken by any outgoing connection between this check and the peer's
/// own bind, one below that range cannot. Ports are walked in order from a start drawn per process, so the
/// tests of one binary never draw the same port twice.
#[allow(dead_code)]
pub fn free_port_on(host: &str) -> u16 {
    use std::sync::OnceLock;
    use std::sync::atomic::{AtomicU32, Ordering};
    const LOW: u32 = 20_000;
    const SPAN: u32 = 12_000;
    static START: OnceLock<u32> = OnceLock::new();
    static NEXT: AtomicU32 = AtomicU32::new(0);
    let start = *START.get_or_init(|| {
        let nanos = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map(|d| d.subsec_nanos())
            .unwrap_or(0);
        (std::process::id().wrapping_mul(2_654_435_761) ^ nanos) % SPAN
    });
    for _ in 0..SPAN {
        let n = NEXT.fetch_add(1, Ordering::Relaxed);
        let port = (LOW + (start + n) % SPAN) as u16;
        if std::net::TcpListener::bind((host, port)).is_ok() {
            return port;
        }
    }
    panic!("no free port on {host} between {LOW} and {}", LOW + SPAN)
}

/// A free port on loopback ([`free_port_on`]).
#[allow(dead_code)]
pub fn free_port() -> u16 {
    free_port_on("127.0.0.1")
}

//! PDUs read off an accepted association without copying the data they carry: a P-DATA-TF PDU (PS3.8 §9.3.5) is
//! split off the association's read buffer whole, and its presentation data values are slices of it; every other
//! PDU is parsed by dicom-ul from the same buffer.

use std::ops::Range;

use bytes::{Buf as _, Bytes};
use dicom_ul::association::AsyncAssociation as _;
use dicom_ul::association::AsyncServerAssociation;
use dicom_ul::pdu::{Pdu, read_pdu};
use tokio::io::AsyncReadExt as _;
use tokio::net::TcpStream;

/// Bytes of a PDU header: type, reserved, length (big endian).
const HEADER: usize = 6;
/// The type of a P-DATA-TF PDU.
const P_DATA_TF: u8 = 0x04;

/// One presentation data value of a P-DATA-TF PDU.
#[derive(Debug, Clone, Copy)]
pub struct Pdv<'a> {
    pub context_id: u8,
    /// A command fragment (else a data set fragment).
    pub command: bool,
    /// The last fragment of its command or data set.
    pub last: bool,
    pub data: &'a [u8],
}

/// A checked P-DATA-TF PDU.
#[derive(Debug)]
pub struct PData {
    pdu: Bytes,
    /// (presentation context, message control header, data) of each value, in order.
    values: Vec<(u8, u8, Range<usize>)>,
}

impl PData {
    /// Check the items of the PDU `pdu` (header included).
    fn parse(pdu: Bytes) -> Result<Self, WireError> {
        let mut values = Vec::new();
        let mut at = HEADER;
        while at < pdu.len() {
            // Item length (4), presentation context (1), message control header (1), then the data.
            let Some(head) = pdu.get(at..at + 6) else {
                return Err(WireError::Malformed(
                    "a presentation data value item is cut short",
                ));
            };
            let item = u32::from_be_bytes([head[0], head[1], head[2], head[3]]) as usize;
            if item < 2 {
                return Err(WireError::Malformed(
                    "a presentation data value item shorter than its header",
                ));
            }
            let end = (at + 4)
                .checked_add(item)
                .filter(|&e| e <= pdu.len())
                .ok_or(WireError::Malformed(
                    "a presentation data value item runs past its PDU",
                ))?;
            values.push((head[4], head[5], at + 6..end));
            at = end;
        }
        Ok(Self { pdu, values })
    }

    /// The presentation data values, in order.
    pub fn values(&self) -> impl Iterator<Item = Pdv<'_>> {
        self.values.iter().map(|(context_id, control, range)| Pdv {
            context_id: *context_id,
            command: control & 0x01 != 0,
            last: control & 0x02 != 0,
            data: &self.pdu[range.clone()],
        })
    }
}

/// What arrived on an association.
#[derive(Debug)]
pub enum Incoming {
    Data(PData),
    Other(Pdu),
}

/// Why no PDU could be read.
#[derive(Debug, thiserror::Error)]
pub enum WireError {
    #[error("the connection closed")]
    Closed,
    /// Shown inside [`AssociationEnd::Network`](super::association::AssociationEnd), which names it.
    #[error("{0}")]
    Io(#[from] std::io::Error),
    #[error("a PDU of {length} bytes, over the negotiated maximum of {max}")]
    TooLong { length: u32, max: u32 },
    #[error("malformed PDU: {0}")]
    Malformed(&'static str),
    #[error("malformed PDU: {0}")]
    Other(String),
}

/// The next PDU of `assoc`, whose PDUs may be `max_pdu` bytes long (as this end negotiated).
pub async fn receive(
    assoc: &mut AsyncServerAssociation<TcpStream>,
    max_pdu: u32,
) -> Result<Incoming, WireError> {
    let (socket, buf) = assoc.get_mut();
    loop {
        if buf.len() >= HEADER {
            let length = u32::from_be_bytes([buf[2], buf[3], buf[4], buf[5]]);
            if length > max_pdu {
                return Err(WireError::TooLong {
                    length,
                    max: max_pdu,
                });
            }
            let whole = HEADER + length as usize;
            if buf.len() >= whole {
                if buf[0] == P_DATA_TF {
                    return Ok(Incoming::Data(PData::parse(buf.split_to(whole).freeze())?));
                }
                let mut cursor = std::io::Cursor::new(&buf[..whole]);
                let pdu = read_pdu(&mut cursor, max_pdu, true)
                    .map_err(|e| WireError::Other(e.to_string()))?
                    .ok_or(WireError::Malformed("a PDU shorter than its length"))?;
                buf.advance(whole);
                return Ok(Incoming::Other(pdu));
            }
            // Room for the rest of this PDU (at most the negotiated maximum), so that it arrives in as few
            // reads as the network allows.
            buf.reserve(whole - buf.len());
        } else {
            buf.reserve(HEADER - buf.len());
        }
        if socket.read_buf(buf).await? == 0 {
            return Err(WireError::Closed);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pdu(items: &[(u32, u8, u8, &[u8])]) -> Bytes {
        let mut body = Vec::new();
        for (len, ctx, ctl, data) in items {
            body.extend_from_slice(&len.to_be_bytes());
            body.extend_from_slice(&[*ctx, *ctl]);
            body.extend_from_slice(data);
        }
        let mut out = vec![P_DATA_TF, 0];
        out.extend_from_slice(&(body.len() as u32).to_be_bytes());
        out.extend_from_slice(&body);
        Bytes::from(out)
    }

    #[test]
    fn the_values_of_a_p_data_pdu_are_slices_of_it() {
        let p = PData::parse(pdu(&[
            (5, 1, 0x03, b"abc"),
            (2, 3, 0x00, b""),
            (4, 5, 0x02, b"xy"),
        ]))
        .unwrap();
        let v: Vec<_> = p
            .values()
            .map(|v| (v.context_id, v.command, v.last, v.data.to_vec()))
            .collect();
        assert_eq!(
            v,
            vec![
                (1, true, true, b"abc".to_vec()),
                (3, false, false, vec![]),
                (5, false, true, b"xy".to_vec()),
            ]
        );
        assert_eq!(PData::parse(pdu(&[])).unwrap().values().count(), 0);
    }

    #[test]
    fn items_that_do_not_fit_their_pdu_are_refused() {
        for bad in [
            pdu(&[(1, 1, 0x03, b"")]),        // shorter than its own header
            pdu(&[(9, 1, 0x03, b"abc")]),     // runs past the PDU
            pdu(&[(u32::MAX, 1, 0x03, b"")]), // a length that overflows
        ] {
            assert!(matches!(PData::parse(bad), Err(WireError::Malformed(_))));
        }
        // Three bytes after the last item: not a whole item header.
        let mut cut = pdu(&[(3, 1, 0x03, b"a")]).to_vec();
        cut.extend_from_slice(&[0, 0, 0]);
        let n = (cut.len() - HEADER) as u32;
        cut[2..6].copy_from_slice(&n.to_be_bytes());
        assert!(matches!(
            PData::parse(Bytes::from(cut)),
            Err(WireError::Malformed(_))
        ));
    }
}

//! The entropy-coded data of a 12-bit sequential scan: Huffman tables, the bit stream, and the blocks of
//! one component through the inverse DCT into the image.

use super::idct::idct_islow;

/// `zigzag[k]`: the natural (row-major) index of the `k`-th coefficient in zig-zag order.
pub(super) const ZIGZAG: [usize; 64] = [
    0, 1, 8, 16, 9, 2, 3, 10, 17, 24, 32, 25, 18, 11, 4, 5, 12, 19, 26, 33, 40, 48, 41, 34, 27, 20,
    13, 6, 7, 14, 21, 28, 35, 42, 49, 56, 57, 50, 43, 36, 29, 22, 15, 23, 30, 37, 44, 51, 58, 59,
    52, 45, 38, 31, 39, 46, 53, 60, 61, 54, 47, 55, 62, 63,
];

/// A Huffman table as T.81 F.2.2.3 decodes with it: per code length, the largest code and where its values
/// start.
#[derive(Clone)]
pub(super) struct Huffman {
    /// `maxcode[l]`: the largest code of length `l` (1–16), −1 when there is none.
    maxcode: [i32; 17],
    /// `valptr[l] − mincode[l]`: added to a code of length `l` it gives the index of its value.
    offset: [i32; 17],
    values: Vec<u8>,
}

impl Huffman {
    pub(super) fn new(counts: &[u8], values: &[u8]) -> Result<Self, String> {
        let mut maxcode = [-1i32; 17];
        let mut offset = [0i32; 17];
        let (mut code, mut k) = (0i32, 0i32);
        for l in 1..=16 {
            let n = i32::from(counts[l - 1]);
            if n > 0 {
                offset[l] = k - code;
                code += n;
                k += n;
                maxcode[l] = code - 1;
                if code > (1 << l) {
                    return Err("a Huffman table with more codes than fit".into());
                }
            }
            code <<= 1;
        }
        Ok(Self {
            maxcode,
            offset,
            values: values.to_vec(),
        })
    }

    fn decode(&self, bits: &mut Bits<'_>) -> Result<u8, String> {
        let mut code = 0i32;
        for l in 1..=16 {
            code = (code << 1) | bits.bit() as i32;
            if code <= self.maxcode[l] {
                let i = code + self.offset[l];
                return usize::try_from(i)
                    .ok()
                    .and_then(|i| self.values.get(i))
                    .copied()
                    .ok_or_else(|| "a Huffman code without a value".into());
            }
        }
        Err("a bit sequence that is no Huffman code".into())
    }
}

/// The entropy-coded bits of a scan: stuffed zero bytes removed, zero bits once a marker is reached.
pub(super) struct Bits<'a> {
    d: &'a [u8],
    p: usize,
    acc: u32,
    n: u32,
    /// A marker (other than a stuffed byte) was reached at `p`.
    at_marker: bool,
}

impl<'a> Bits<'a> {
    pub(super) fn new(d: &'a [u8]) -> Self {
        Self {
            d,
            p: 0,
            acc: 0,
            n: 0,
            at_marker: false,
        }
    }

    fn bit(&mut self) -> u32 {
        if self.n == 0 {
            let byte = self.next_byte();
            self.acc = u32::from(byte);
            self.n = 8;
        }
        self.n -= 1;
        (self.acc >> self.n) & 1
    }

    fn next_byte(&mut self) -> u8 {
        if self.at_marker {
            return 0;
        }
        match (self.d.get(self.p), self.d.get(self.p + 1)) {
            (Some(0xFF), Some(0x00)) => {
                self.p += 2;
                0xFF
            }
            (Some(0xFF), _) | (None, _) => {
                self.at_marker = true;
                0
            }
            (Some(&b), _) => {
                self.p += 1;
                b
            }
        }
    }

    /// `s` bits as an unsigned number.
    fn receive(&mut self, s: u32) -> i32 {
        let mut v = 0i32;
        for _ in 0..s {
            v = (v << 1) | self.bit() as i32;
        }
        v
    }

    /// At a restart interval's end: the rest of the byte dropped, the RSTn marker read.
    fn restart(&mut self) -> Result<(), String> {
        self.n = 0;
        if !self.at_marker {
            // Fill bits: the marker follows.
            match (self.d.get(self.p), self.d.get(self.p + 1)) {
                (Some(0xFF), Some(m)) if (0xD0..=0xD7).contains(m) => {}
                _ => return Err("a restart marker is missing".into()),
            }
        }
        let mut p = self.p;
        while self.d.get(p) == Some(&0xFF) {
            p += 1;
        }
        match self.d.get(p) {
            Some(m) if (0xD0..=0xD7).contains(m) => {
                self.p = p + 1;
                self.at_marker = false;
                Ok(())
            }
            _ => Err("a restart marker is missing".into()),
        }
    }

    /// Bytes of the scan read so far (up to the marker that ends it).
    pub(super) fn consumed_bytes(&self) -> usize {
        self.p
    }
}

/// The value of `s` received bits as a signed coefficient (T.81 F.2.2.1, EXTEND).
fn extend(v: i32, s: u32) -> i32 {
    if s == 0 {
        0
    } else if v < (1 << (s - 1)) {
        v - (1 << s) + 1
    } else {
        v
    }
}

/// Decode the scan of one component into a `rows` × `columns` image.
pub(super) fn scan(
    bits: &mut Bits<'_>,
    rows: usize,
    columns: usize,
    q: &[u16; 64],
    dc: &Huffman,
    ac: &Huffman,
    restart: usize,
) -> Result<Vec<u16>, String> {
    let (bw, bh) = (columns.div_ceil(8), rows.div_ceil(8));
    let mut img = vec![0u16; rows * columns];
    // Quantisation in natural order, as the inverse DCT reads it.
    let mut qn = [0i64; 64];
    for (&z, &v) in ZIGZAG.iter().zip(q) {
        qn[z] = i64::from(v);
    }
    let mut pred = 0i32;
    // Coefficients are kept in 16 bits as IJG keeps them (`JCOEF`), which also bounds the inverse DCT's
    // arithmetic whatever a damaged stream holds.
    let mut block = [0i16; 64];
    let mut out = [0u16; 64];
    for b in 0..bw * bh {
        if restart > 0 && b > 0 && b % restart == 0 {
            bits.restart()?;
            pred = 0;
        }
        block.fill(0);
        let t = u32::from(dc.decode(bits)?);
        if t > 15 {
            return Err(format!("a DC difference of {t} bits"));
        }
        pred = pred.wrapping_add(extend(bits.receive(t), t));
        block[0] = pred as i16;
        let mut k = 1;
        while k < 64 {
            let rs = ac.decode(bits)?;
            let (run, s) = (usize::from(rs >> 4), u32::from(rs & 15));
            if s == 0 {
                if run == 15 {
                    k += 16;
                    continue;
                }
                break;
            }
            k += run;
            if k > 63 {
                return Err("AC coefficients past the end of a block".into());
            }
            block[ZIGZAG[k]] = extend(bits.receive(s), s) as i16;
            k += 1;
        }
        idct_islow(&block, &qn, &mut out);
        let (by, bx) = (b / bw, b % bw);
        for y in 0..8 {
            let row = by * 8 + y;
            if row >= rows {
                break;
            }
            let x0 = bx * 8;
            let n = 8.min(columns - x0);
            img[row * columns + x0..row * columns + x0 + n].copy_from_slice(&out[y * 8..y * 8 + n]);
        }
    }
    Ok(img)
}

//! The IJG integer inverse DCT and its range limiting, at 12-bit sample precision.

// The IJG integer inverse DCT (jidctint.c, `jpeg_idct_islow`) at 12-bit sample precision: constants scaled
// by 2¹³, one extra bit of precision between the passes.
const CONST_BITS: u32 = 13;
const PASS1_BITS: u32 = 1;
const FIX_0_298631336: i64 = 2446;
const FIX_0_390180644: i64 = 3196;
const FIX_0_541196100: i64 = 4433;
const FIX_0_765366865: i64 = 6270;
const FIX_0_899976223: i64 = 7373;
const FIX_1_175875602: i64 = 9633;
const FIX_1_501321110: i64 = 12299;
const FIX_1_847759065: i64 = 15137;
const FIX_1_961570560: i64 = 16069;
const FIX_2_053119869: i64 = 16819;
const FIX_2_562915447: i64 = 20995;
const FIX_3_072711026: i64 = 25172;

fn descale(x: i64, n: u32) -> i64 {
    (x + (1 << (n - 1))) >> n
}

/// One 8-point pass over `v` (in[0..8]); returns the eight outputs before descaling, in order 0–7.
#[inline(always)]
fn idct_1d(v: [i64; 8], dc_shift: u32) -> [i64; 8] {
    // Even part.
    let (z2, z3) = (v[2], v[6]);
    let z1 = (z2 + z3) * FIX_0_541196100;
    let tmp2 = z1 + z3 * -FIX_1_847759065;
    let tmp3 = z1 + z2 * FIX_0_765366865;
    let tmp0 = (v[0] + v[4]) << dc_shift;
    let tmp1 = (v[0] - v[4]) << dc_shift;
    let (tmp10, tmp13) = (tmp0 + tmp3, tmp0 - tmp3);
    let (tmp11, tmp12) = (tmp1 + tmp2, tmp1 - tmp2);
    // Odd part.
    let (mut t0, mut t1, mut t2, mut t3) = (v[7], v[5], v[3], v[1]);
    let mut z1 = t0 + t3;
    let mut z2 = t1 + t2;
    let mut z3 = t0 + t2;
    let mut z4 = t1 + t3;
    let z5 = (z3 + z4) * FIX_1_175875602;
    t0 *= FIX_0_298631336;
    t1 *= FIX_2_053119869;
    t2 *= FIX_3_072711026;
    t3 *= FIX_1_501321110;
    z1 *= -FIX_0_899976223;
    z2 *= -FIX_2_562915447;
    z3 *= -FIX_1_961570560;
    z4 *= -FIX_0_390180644;
    z3 += z5;
    z4 += z5;
    t0 += z1 + z3;
    t1 += z2 + z4;
    t2 += z2 + z3;
    t3 += z1 + z4;
    [
        tmp10 + t3,
        tmp11 + t2,
        tmp12 + t1,
        tmp13 + t0,
        tmp13 - t0,
        tmp12 - t1,
        tmp11 - t2,
        tmp10 - t3,
    ]
}

/// IJG's post-IDCT range limit at 12 bits: the value masked to 14 bits, then centred and clamped as its
/// table does (`prepare_range_limit_table`).
pub(super) fn range_limit(x: i64) -> u16 {
    let y = (x & 0x3FFF) as i32;
    match y {
        0..=2047 => (y + 2048) as u16,
        2048..=8191 => 4095,
        8192..=14335 => 0,
        _ => (y - 14336) as u16,
    }
}

pub(super) fn idct_islow(coef: &[i16; 64], q: &[i64; 64], out: &mut [u16; 64]) {
    let mut ws = [0i64; 64];
    for c in 0..8 {
        let v = std::array::from_fn(|r| i64::from(coef[r * 8 + c]) * q[r * 8 + c]);
        let o = idct_1d(v, CONST_BITS);
        for r in 0..8 {
            ws[r * 8 + c] = descale(o[r], CONST_BITS - PASS1_BITS);
        }
    }
    for r in 0..8 {
        let v = std::array::from_fn(|c| ws[r * 8 + c]);
        let o = idct_1d(v, CONST_BITS);
        for c in 0..8 {
            out[r * 8 + c] = range_limit(descale(o[c], CONST_BITS + PASS1_BITS + 3));
        }
    }
}

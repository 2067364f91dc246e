//! The decoder against the exact inverse DCT and hand-made streams.

use super::idct::{idct_islow, range_limit};
use super::scan::ZIGZAG;
use super::*;

/// The orthonormal 2-D inverse DCT in f64, the definition the integer one approximates.
fn idct_exact(coef: &[i64; 64]) -> [f64; 64] {
    let c = |u: usize| if u == 0 { (0.5f64).sqrt() } else { 1.0 };
    std::array::from_fn(|i| {
        let (y, x) = (i / 8, i % 8);
        let mut s = 0.0;
        for v in 0..8 {
            for u in 0..8 {
                s += c(u)
                    * c(v)
                    * coef[v * 8 + u] as f64
                    * (((2 * x + 1) * u) as f64 * std::f64::consts::PI / 16.0).cos()
                    * (((2 * y + 1) * v) as f64 * std::f64::consts::PI / 16.0).cos();
            }
        }
        s / 4.0 + 2048.0
    })
}

#[test]
fn the_integer_inverse_dct_is_within_one_of_the_exact_one() {
    let mut seed = 12345u64;
    let mut rnd = |m: i64| {
        seed = seed
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        ((seed >> 33) as i64 % (2 * m + 1)) - m
    };
    let ones = [1i64; 64];
    for trial in 0..200 {
        let mut coef = [0i16; 64];
        coef[0] = rnd(8000) as i16;
        for k in 1..(1 + trial % 63) {
            coef[ZIGZAG[k]] = (rnd(600) / (k as i64)) as i16;
        }
        let mut out = [0u16; 64];
        idct_islow(&coef, &ones, &mut out);
        let exact = idct_exact(&std::array::from_fn(|i| i64::from(coef[i])));
        for i in 0..64 {
            let want = exact[i].round().clamp(0.0, 4095.0);
            assert!(
                (f64::from(out[i]) - want).abs() <= 1.0,
                "trial {trial} sample {i}: {} vs {}",
                out[i],
                exact[i]
            );
        }
    }
}

#[test]
fn extreme_coefficients_and_quantisation_stay_in_range() {
    let q = [i64::from(u16::MAX); 64];
    for fill in [i16::MIN, i16::MAX, -1, 1] {
        let mut coef = [fill; 64];
        coef[63] = i16::MIN;
        let mut out = [0u16; 64];
        idct_islow(&coef, &q, &mut out);
        assert!(out.iter().all(|&v| v <= 4095));
    }
}

#[test]
fn the_range_limit_clamps_as_the_ijg_table_does() {
    assert_eq!(range_limit(0), 2048);
    assert_eq!(range_limit(-2048), 0);
    assert_eq!(range_limit(2047), 4095);
    assert_eq!(range_limit(5000), 4095);
    assert_eq!(range_limit(-5000), 0);
    assert_eq!(range_limit(-1), 2047);
}

/// A stream of one 8 × 8 block whose DC difference is `dc` (other coefficients zero), with flat
/// quantisation `q`: DC table with the categories 0–15 as 4-bit codes, AC table with EOB only.
fn one_block(dc: i32, q: u8) -> Vec<u8> {
    let mut s = vec![0xFF, 0xD8];
    s.extend([0xFF, 0xDB, 0, 67, 0x00]);
    s.extend([q; 64]);
    s.extend([0xFF, 0xC1, 0, 11, 12, 0, 8, 0, 8, 1, 1, 0x11, 0]);
    // DC: 16 codes of 4 bits (categories 0–15).
    s.extend([0xFF, 0xC4, 0, 19 + 16, 0x00]);
    s.extend([0, 0, 0, 16, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0]);
    s.extend(0..16u8);
    // AC: EOB as the one code "0".
    s.extend([
        0xFF, 0xC4, 0, 20, 0x10, 1, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0x00,
    ]);
    s.extend([0xFF, 0xDA, 0, 8, 1, 1, 0x00, 0, 63, 0]);
    // Bits: category (4), value (category bits), EOB (1), padded with ones.
    let cat = if dc == 0 {
        0
    } else {
        32 - dc.unsigned_abs().leading_zeros()
    };
    let value = if dc >= 0 {
        dc as u32
    } else {
        (dc - 1) as u32 & ((1 << cat) - 1)
    };
    let mut acc: u64 = u64::from(cat);
    let mut n = 4;
    acc = (acc << cat) | u64::from(value);
    n += cat;
    acc <<= 1;
    n += 1;
    while n % 8 != 0 {
        acc = (acc << 1) | 1;
        n += 1;
    }
    for i in (0..n / 8).rev() {
        let b = (acc >> (8 * i)) as u8;
        s.push(b);
        if b == 0xFF {
            s.push(0);
        }
    }
    s.extend([0xFF, 0xD9]);
    s
}

#[test]
fn a_flat_block_decodes_to_its_dc_level() {
    for (dc, q, want) in [
        (0, 1, 2048u16),
        (800, 2, 2248),
        (-1000, 4, 1548),
        (8000, 8, 4095),
    ] {
        let s = one_block(dc, q);
        assert!(is_12bit_dct(&s));
        let img = decode(&s, 8, 8).unwrap();
        // A flat block: DC·q/8 above the centre.
        assert!(img.iter().all(|&v| v == want), "{dc}·{q}: {:?}", &img[..8]);
    }
}

#[test]
fn wrong_sizes_other_kinds_and_damage_are_named_refusals() {
    let s = one_block(100, 1);
    assert!(decode(&s, 8, 16).unwrap_err().contains("8×8"));
    let mut eight_bit = s.clone();
    let sof = eight_bit
        .windows(2)
        .position(|w| w == [0xFF, 0xC1])
        .unwrap();
    eight_bit[sof + 4] = 8;
    assert!(!is_12bit_dct(&eight_bit));
    assert!(decode(&eight_bit, 8, 8).unwrap_err().contains("8-bit"));
    let mut progressive = s.clone();
    progressive[sof + 1] = 0xC2;
    assert!(decode(&progressive, 8, 8).unwrap_err().contains("SOF2"));
    let mut colour = s.clone();
    colour[sof + 9] = 3;
    assert!(decode(&colour, 8, 8).is_err());
    for cut in 0..s.len() {
        // Every prefix is refused or decodes; none panics.
        let _ = decode(&s[..cut], 8, 8);
    }
    let mut flipped = s.clone();
    for b in flipped.iter_mut().skip(3).step_by(5) {
        *b ^= 0xA5;
    }
    let _ = decode(&flipped, 8, 8);
    assert_eq!(decode_frames(&[&s, &s], 2, 8, 8).unwrap().len(), 2 * 64 * 2);
}

#[test]
fn mutated_streams_are_decoded_or_refused_never_a_panic() {
    let base = one_block(-700, 3);
    let mut seed = 99u64;
    let mut next = |m: usize| {
        seed = seed
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (seed >> 33) as usize % m
    };
    for _ in 0..20_000 {
        let mut s = base.clone();
        for _ in 0..1 + next(4) {
            let at = next(s.len());
            match next(3) {
                0 => s[at] = next(256) as u8,
                1 => {
                    s.remove(at);
                }
                _ => s.insert(at, [0xFF, 0x00, 0xD0, 0xDD, 0xC4][next(5)]),
            }
        }
        let (rows, columns) = [(8, 8), (8, 16), (1, 1), (9, 7)][next(4)];
        if let Ok(img) = decode(&s, rows, columns) {
            assert_eq!(img.len(), rows * columns);
            assert!(img.iter().all(|&v| v <= 4095));
        }
    }
}

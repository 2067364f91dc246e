use super::*;

const EXPLICIT: Encoding = Encoding {
    explicit: true,
    big_endian: false,
};

#[test]
fn a_length_past_the_end_is_found_and_a_fitting_one_is_not() {
    // (0028,0010) US 2 bytes, then (7FE0,0010) OW with 8 bytes.
    let mut d = Vec::new();
    d.extend_from_slice(&[0x28, 0x00, 0x10, 0x00, b'U', b'S', 2, 0, 4, 0]);
    d.extend_from_slice(&[0xE0, 0x7F, 0x10, 0x00, b'O', b'W', 0, 0, 8, 0, 0, 0]);
    d.extend_from_slice(&[0u8; 8]);
    assert_eq!(dataset(&d, EXPLICIT), Ok(d.len()));
    let n = d.len();
    d[n - 12..n - 8].copy_from_slice(&0xFFFF_FFF0u32.to_le_bytes());
    assert_eq!(
        dataset(&d, EXPLICIT),
        Err(Defect::Overrun {
            tag: (0x7FE0, 0x0010),
            declared: 0xFFFF_FFF0,
            left: 8
        })
    );
}

#[test]
fn an_unknown_vr_takes_a_four_byte_length_as_the_parser_does() {
    // (0008,0018) with VR "ZZ": reserved 2 bytes then a 4-byte length made of the UID's first bytes.
    let mut d = vec![0x08, 0x00, 0x18, 0x00, b'Z', b'Z', 8, 0];
    d.extend_from_slice(b"1.2.3.4\0");
    assert_eq!(
        dataset(&d, EXPLICIT),
        Err(Defect::Overrun {
            tag: (0x0008, 0x0018),
            declared: u32::from_le_bytes(*b"1.2.") as u64,
            left: 4
        })
    );
}

#[test]
fn sequences_nested_too_deep_are_found_before_parsing() {
    let mut d = Vec::new();
    for _ in 0..=MAX_SEQUENCE_DEPTH {
        // (0008,1115) SQ undefined length, then an item of undefined length.
        d.extend_from_slice(&[
            0x08, 0x00, 0x15, 0x11, b'S', b'Q', 0, 0, 0xFF, 0xFF, 0xFF, 0xFF,
        ]);
        d.extend_from_slice(&[0xFE, 0xFF, 0x00, 0xE0, 0xFF, 0xFF, 0xFF, 0xFF]);
    }
    assert_eq!(
        dataset(&d, EXPLICIT),
        Err(Defect::TooDeep {
            tag: (0x0008, 0x1115)
        })
    );
    // One level fewer is fine.
    let one = 12 + 8;
    assert_eq!(dataset(&d[one..], EXPLICIT), Ok(d.len() - one));
}

#[test]
fn a_binary_value_that_is_not_a_whole_number_of_values_is_refused() {
    // (0028,0102) FD with 2 bytes: dicom-rs would read no value yet count 2 bytes as read.
    let mut d = vec![0x28, 0x00, 0x02, 0x01, b'F', b'D', 2, 0, 7, 0];
    assert_eq!(
        dataset(&d, EXPLICIT),
        Err(Defect::Misaligned {
            tag: (0x0028, 0x0102),
            vr: VR::FD,
            declared: 2,
            unit: 8
        })
    );
    // In implicit VR the dictionary gives the VR: High Bit is US, 3 bytes are refused, 2 are read.
    let implicit = Encoding {
        explicit: false,
        big_endian: false,
    };
    d = vec![0x28, 0x00, 0x02, 0x01, 3, 0, 0, 0, 7, 0, 0];
    assert!(matches!(
        dataset(&d, implicit),
        Err(Defect::Misaligned { unit: 2, .. })
    ));
    d = vec![0x28, 0x00, 0x02, 0x01, 2, 0, 0, 0, 7, 0];
    assert_eq!(dataset(&d, implicit), Ok(d.len()));
}

#[test]
fn the_leading_walk_collects_the_image_attributes_and_stops_at_the_pixel_data_whatever_it_declares()
{
    let mut d = Vec::new();
    // (0008,1140) SQ of undefined length holding one item with a (0008,1150) UI: skipped, not collected.
    d.extend_from_slice(&[
        0x08, 0x00, 0x40, 0x11, b'S', b'Q', 0, 0, 0xFF, 0xFF, 0xFF, 0xFF,
    ]);
    d.extend_from_slice(&[0xFE, 0xFF, 0x00, 0xE0, 0xFF, 0xFF, 0xFF, 0xFF]);
    d.extend_from_slice(&[0x08, 0x00, 0x50, 0x11, b'U', b'I', 2, 0, b'1', 0]);
    d.extend_from_slice(&[0xFE, 0xFF, 0x0D, 0xE0, 0, 0, 0, 0]);
    d.extend_from_slice(&[0xFE, 0xFF, 0xDD, 0xE0, 0, 0, 0, 0]);
    // (0028,0010) Rows = 8192, (0028,0011) Columns = 8192.
    d.extend_from_slice(&[0x28, 0x00, 0x10, 0x00, b'U', b'S', 2, 0, 0x00, 0x20]);
    d.extend_from_slice(&[0x28, 0x00, 0x11, 0x00, b'U', b'S', 2, 0, 0x00, 0x20]);
    let header_len = d.len();
    // (7FE0,0010) OW declaring 128 MiB, of which this prefix holds 16 bytes.
    d.extend_from_slice(&[0xE0, 0x7F, 0x10, 0x00, b'O', b'W', 0, 0]);
    d.extend_from_slice(&(128u32 << 20).to_le_bytes());
    d.extend_from_slice(&[0u8; 16]);
    assert!(
        dataset(&d, EXPLICIT).is_err(),
        "the whole walk sees the overrun"
    );
    let got = leading(&d, EXPLICIT, 0x0028).expect("no defect before the pixel data");
    assert_eq!(
        got,
        Some(vec![
            ((0x0028, 0x0010), &[0x00u8, 0x20][..]),
            ((0x0028, 0x0011), &[0x00u8, 0x20][..]),
        ])
    );
    // A prefix cut before the walk leaves group 0028 answers nothing found yet.
    assert_eq!(leading(&d[..header_len - 4], EXPLICIT, 0x0028), Ok(None));
    // A cut inside a value of the leading groups is an overrun of the prefix.
    let mut long = vec![0x10, 0x00, 0x10, 0x00, b'P', b'N', 0, 0];
    long[6..8].copy_from_slice(&1000u16.to_le_bytes());
    long.extend_from_slice(&[b'A'; 10]);
    assert!(matches!(
        leading(&long, EXPLICIT, 0x0028),
        Err(Defect::Overrun {
            tag: (0x0010, 0x0010),
            ..
        })
    ));
}

use ndarray::Array3;

use super::*;

fn npy(descr: &str, shape: &str, data: &[u8]) -> Vec<u8> {
    let dict = format!("{{'descr': '{descr}', 'fortran_order': False, 'shape': {shape}, }}\n");
    let mut out = MAGIC.to_vec();
    out.extend_from_slice(&[1, 0]);
    out.extend_from_slice(&(dict.len() as u16).to_le_bytes());
    out.extend_from_slice(dict.as_bytes());
    out.extend_from_slice(data);
    out
}

fn limits() -> StreamLimits {
    StreamLimits {
        max_file_bytes: 1 << 20,
        max_elements: 1 << 16,
    }
}

#[test]
fn an_encoded_array_decodes_to_the_same_values_and_aligns_its_data() {
    let a = Array3::from_shape_fn((2, 3, 5), |(i, j, k)| (i * 100 + j * 10 + k) as f32 - 7.5);
    let bytes = encode_f32(a.view());
    let h = parse_header(&bytes).unwrap().unwrap();
    assert_eq!(h.data_offset % 64, 0);
    assert_eq!(h.shape, [2, 3, 5]);
    assert_eq!(decode_f32(&bytes).unwrap(), a.into_dyn());
}

#[test]
fn float64_and_big_endian_uint16_convert_to_f32() {
    let d: Vec<u8> = [1.5f64, -2.25]
        .iter()
        .flat_map(|v| v.to_le_bytes())
        .collect();
    let a = decode_f32(&npy("<f8", "(2,)", &d)).unwrap();
    assert_eq!(a.as_slice().unwrap(), &[1.5, -2.25]);
    let d: Vec<u8> = [300u16, 7].iter().flat_map(|v| v.to_be_bytes()).collect();
    let a = decode_f32(&npy(">u2", "(1, 2)", &d)).unwrap();
    assert_eq!(a.as_slice().unwrap(), &[300.0, 7.0]);
}

#[test]
fn malformed_and_unsupported_headers_are_named() {
    assert!(matches!(
        parse_header(b"NUMPY\x01\x00"),
        Err(NpyError::Malformed(_))
    ));
    assert!(matches!(
        parse_header(&npy("<i8", "(2,)", &[0; 16])),
        Err(NpyError::UnsupportedDtype(d)) if d == "<i8"
    ));
    let f = npy("<f4", "(2,)", &[0; 8]);
    let at = f
        .windows(5)
        .position(|w| w == b"False")
        .expect("the header names fortran_order");
    let mut fortran = f.clone();
    fortran[at..at + 5].copy_from_slice(b"True ");
    assert_eq!(parse_header(&fortran), Err(NpyError::FortranOrder));
    assert!(matches!(
        parse_header(&npy("<f4", "(2, -1)", &[])),
        Err(NpyError::Malformed(_))
    ));
    assert_eq!(parse_header(&f[..20]), Ok(None));
}

#[test]
fn a_stream_checks_shape_size_finiteness_and_length_across_chunk_boundaries() {
    let values = [1.0f32, 2.0, f32::NAN, 4.0];
    let data: Vec<u8> = values.iter().flat_map(|v| v.to_le_bytes()).collect();
    let file = npy("<f4", "(2, 2)", &data);
    // NaN at flat index 2 is found even when chunks split elements.
    let mut s = NpyStream::new(limits(), Some(vec![2, 2]));
    let err = file.chunks(3).try_for_each(|c| s.feed(c));
    assert_eq!(err, Err(StreamError::NonFinite { index: 2 }));

    let good: Vec<u8> = [1.0f32, 2.0, 3.0, 4.0]
        .iter()
        .flat_map(|v| v.to_le_bytes())
        .collect();
    let file = npy("<f4", "(2, 2)", &good);
    let mut s = NpyStream::new(limits(), Some(vec![2, 2]));
    file.chunks(5).try_for_each(|c| s.feed(c)).unwrap();
    let (h, n, sha) = s.finish().unwrap();
    assert_eq!((h.shape, n, sha.len()), (vec![2, 2], file.len() as u64, 64));

    let mut s = NpyStream::new(limits(), Some(vec![4]));
    assert!(matches!(
        s.feed(&file),
        Err(StreamError::ShapeMismatch { .. })
    ));
    let mut s = NpyStream::new(limits(), None);
    s.feed(&file[..file.len() - 1]).unwrap();
    assert!(matches!(s.finish(), Err(StreamError::Truncated { .. })));
    let mut s = NpyStream::new(limits(), None);
    let mut long = file.clone();
    long.push(0);
    assert!(matches!(
        s.feed(&long),
        Err(StreamError::TrailingBytes { .. })
    ));
    let huge = npy("<f4", "(100000, 100000)", &[]);
    let mut s = NpyStream::new(limits(), None);
    assert!(matches!(s.feed(&huge), Err(StreamError::TooLarge { .. })));
}

//! Hostile DICOM input: small valid files built here with dicom-object, then truncated, corrupted and bent
//! in the ways real breakage and attackers bend them. The reader must never panic (a panic hook counts
//! panics on the reading thread, including those a `catch_unwind` would hide), must refuse bad input with a
//! typed error and a stable code, and must never allocate more than a small multiple of the file's size
//! (a counting global allocator measures the peak on the reading thread).

mod common;

use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;
use std::sync::Once;

use ctrecon::dicom::{DicomError, Instance, ReadLimits, read_bytes};
use dicom_core::value::PrimitiveValue;
use dicom_core::{DataElement, Tag, VR, dicom_value};
use dicom_dictionary_std::tags;
use dicom_object::{FileMetaTableBuilder, InMemDicomObject};

// ---------------------------------------------------------------------------------------------------------
// Measuring: allocation peak and panics, per thread.

thread_local! {
    static LIVE: Cell<isize> = const { Cell::new(0) };
    static PEAK: Cell<isize> = const { Cell::new(0) };
    static PANICS: Cell<usize> = const { Cell::new(0) };
}

fn track(delta: isize) {
    let _ = LIVE.try_with(|live| {
        let v = live.get() + delta;
        live.set(v);
        let _ = PEAK.try_with(|p| {
            if v > p.get() {
                p.set(v)
            }
        });
    });
}

/// The system allocator, counting the bytes live on each thread.
struct Counting;

// SAFETY: every call forwards to `System` with the caller's layout unchanged; the bookkeeping only touches
// const-initialised thread-locals (no allocation, no destructor).
#[allow(unsafe_code)] // a counting allocator wraps the system one
unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        // SAFETY: forwarded as is.
        let p = unsafe { System.alloc(layout) };
        if !p.is_null() {
            track(layout.size() as isize);
        }
        p
    }
    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        // SAFETY: forwarded as is.
        let p = unsafe { System.alloc_zeroed(layout) };
        if !p.is_null() {
            track(layout.size() as isize);
        }
        p
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        // SAFETY: forwarded as is.
        unsafe { System.dealloc(ptr, layout) };
        track(-(layout.size() as isize));
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        // SAFETY: forwarded as is.
        let p = unsafe { System.realloc(ptr, layout, new_size) };
        if !p.is_null() {
            track(new_size as isize - layout.size() as isize);
        }
        p
    }
}

#[global_allocator]
static ALLOCATOR: Counting = Counting;

fn count_panics() {
    static HOOK: Once = Once::new();
    HOOK.call_once(|| {
        let default = std::panic::take_hook();
        std::panic::set_hook(Box::new(move |info| {
            // A panic inside a contained third-party codec is answered as an error of the file; one line is
            // printed for it (a symbolised backtrace would count against the reader's allocation peak).
            if ctrecon::dicom::panic_is_contained() {
                eprintln!("contained: {info}");
                return;
            }
            let _ = PANICS.try_with(|p| p.set(p.get() + 1));
            default(info);
        }));
    });
}

/// Allowed peak allocation while reading a file of `len` bytes: the decoded f32 samples of 8-bit pixels take
/// 4× their stored size, the parsed data set and the decoder's copy one more each. A fixed 4 MiB covers what
/// no input sizes: the data dictionary's one-time index, and the stack trace every dicom-rs parse error
/// captures (snafu 0.9 forces the capture; about 2 MB here).
fn allowance(len: usize) -> isize {
    (6 * len + (4 << 20)) as isize
}

/// Read `bytes` on this thread, asserting no panic and an allocation peak within [`allowance`].
fn read_with(what: &str, bytes: &[u8], limits: &ReadLimits) -> Result<Instance, DicomError> {
    read_within(what, bytes, limits, allowance(bytes.len()))
}

/// Read `bytes` on this thread, asserting no panic and an allocation peak of at most `allowed` bytes.
fn read_within(
    what: &str,
    bytes: &[u8],
    limits: &ReadLimits,
    allowed: isize,
) -> Result<Instance, DicomError> {
    count_panics();
    let panics0 = PANICS.with(|p| p.get());
    let live0 = LIVE.with(|l| l.get());
    PEAK.with(|p| p.set(live0));
    let r = std::panic::catch_unwind(|| read_bytes("hostile.dcm", bytes, limits));
    let peak = PEAK.with(|p| p.get()) - live0;
    let panics = PANICS.with(|p| p.get()) - panics0;
    assert_eq!(panics, 0, "{what}: the reader panicked");
    let r = r.unwrap_or_else(|_| panic!("{what}: the reader panicked"));
    assert!(
        peak <= allowed,
        "{what}: peak allocation {peak} bytes for a file of {} bytes ({:?})",
        bytes.len(),
        r.as_ref().map(|i| i.slices.len())
    );
    r
}

fn read(what: &str, bytes: &[u8]) -> Result<Instance, DicomError> {
    read_with(what, bytes, &ReadLimits::default())
}

/// The code of a refusal (the test fails if the file was read).
fn refusal(what: &str, bytes: &[u8]) -> &'static str {
    match read(what, bytes) {
        Ok(_) => panic!("{what}: read, but should be refused"),
        Err(e) => {
            assert!(e.to_string().contains("hostile.dcm"), "{what}: {e}");
            e.code()
        }
    }
}

// ---------------------------------------------------------------------------------------------------------
// Fixtures.

const EXPLICIT_LE: &str = "1.2.840.10008.1.2.1";
const IMPLICIT_LE: &str = "1.2.840.10008.1.2";

fn el(tag: Tag, vr: VR, v: PrimitiveValue) -> DataElement<InMemDicomObject> {
    DataElement::new(tag, vr, v)
}

/// A CT image `rows × columns`, 16-bit signed, pixel (r, c) = 100·r + c − 500, slope 1, intercept −1024.
fn ct(rows: u16, columns: u16) -> InMemDicomObject {
    let pixels: Vec<i16> = (0..rows as i32)
        .flat_map(|r| (0..columns as i32).map(move |c| (100 * r + c - 500) as i16))
        .collect();
    InMemDicomObject::from_element_iter([
        el(
            tags::SOP_CLASS_UID,
            VR::UI,
            PrimitiveValue::from("1.2.840.10008.5.1.4.1.1.2"),
        ),
        el(
            tags::SOP_INSTANCE_UID,
            VR::UI,
            PrimitiveValue::from("1.2.826.0.1.3680043.2.1125.1.1"),
        ),
        el(
            tags::STUDY_INSTANCE_UID,
            VR::UI,
            PrimitiveValue::from("1.2.826.0.1.3680043.2.1125.1.2"),
        ),
        el(
            tags::SERIES_INSTANCE_UID,
            VR::UI,
            PrimitiveValue::from("1.2.826.0.1.3680043.2.1125.1.3"),
        ),
        el(tags::MODALITY, VR::CS, PrimitiveValue::from("CT")),
        el(
            tags::IMAGE_POSITION_PATIENT,
            VR::DS,
            PrimitiveValue::from("-10\\-20\\30"),
        ),
        el(
            tags::IMAGE_ORIENTATION_PATIENT,
            VR::DS,
            PrimitiveValue::from("1\\0\\0\\0\\1\\0"),
        ),
        el(
            tags::PIXEL_SPACING,
            VR::DS,
            PrimitiveValue::from("0.5\\0.5"),
        ),
        el(tags::SAMPLES_PER_PIXEL, VR::US, dicom_value!(U16, [1])),
        el(
            tags::PHOTOMETRIC_INTERPRETATION,
            VR::CS,
            PrimitiveValue::from("MONOCHROME2"),
        ),
        el(tags::ROWS, VR::US, dicom_value!(U16, [rows])),
        el(tags::COLUMNS, VR::US, dicom_value!(U16, [columns])),
        el(tags::BITS_ALLOCATED, VR::US, dicom_value!(U16, [16])),
        el(tags::BITS_STORED, VR::US, dicom_value!(U16, [16])),
        el(tags::HIGH_BIT, VR::US, dicom_value!(U16, [15])),
        el(tags::PIXEL_REPRESENTATION, VR::US, dicom_value!(U16, [1])),
        el(
            tags::RESCALE_INTERCEPT,
            VR::DS,
            PrimitiveValue::from("-1024"),
        ),
        el(tags::RESCALE_SLOPE, VR::DS, PrimitiveValue::from("1")),
        el(
            tags::PIXEL_DATA,
            VR::OW,
            PrimitiveValue::U16(pixels.iter().map(|&v| v as u16).collect()),
        ),
    ])
}

/// `obj` as a Part 10 file (preamble, `DICM`, meta group) in transfer syntax `ts`.
fn part10(obj: InMemDicomObject, ts: &str) -> Vec<u8> {
    let file = obj
        .with_meta(FileMetaTableBuilder::new().transfer_syntax(ts))
        .expect("meta");
    let mut out = Vec::new();
    file.write_all(&mut out).expect("write");
    out
}

/// An explicit VR little endian file whose meta group names an unregistered transfer syntax of the same length.
fn unknown_ts() -> Vec<u8> {
    let mut bytes = part10(ct(8, 10), EXPLICIT_LE);
    let at = find_tag(&bytes, Tag(0x0002, 0x0010)) + 8;
    assert_eq!(&bytes[at..at + 20], b"1.2.840.10008.1.2.1\0");
    bytes[at..at + 20].copy_from_slice(b"1.2.3.4.5.6.7.8.9.10");
    bytes
}

/// Offset of the first element with this tag (little endian) after the preamble.
fn find_tag(bytes: &[u8], tag: Tag) -> usize {
    let mut needle = tag.0.to_le_bytes().to_vec();
    needle.extend_from_slice(&tag.1.to_le_bytes());
    bytes[132..]
        .windows(4)
        .position(|w| w == needle)
        .map(|p| p + 132)
        .expect("tag present")
}

// ---------------------------------------------------------------------------------------------------------
// Part 1: no panic, a typed refusal.

#[test]
fn the_intact_fixture_reads_back_its_pixels() {
    let bytes = part10(ct(8, 10), EXPLICIT_LE);
    let inst = read("intact", &bytes).expect("an intact file reads");
    let s = &inst.slices[0];
    assert_eq!((s.rows, s.columns), (8, 10));
    assert_eq!(s.stored[0], -500.0);
    assert_eq!(s.stored[7 * 10 + 9], 209.0);
    assert_eq!((s.rescale_slope, s.rescale_intercept), (1.0, -1024.0));
    assert_eq!(s.position_mm, Some([-10.0, -20.0, 30.0]));
}

#[test]
fn a_file_cut_at_any_offset_is_refused_with_a_code_and_never_panics() {
    for ts in [EXPLICIT_LE, IMPLICIT_LE] {
        let bytes = part10(ct(8, 10), ts);
        let n = bytes.len();
        // Every offset of the preamble, meta group and header, then every 7th byte to the end.
        let cuts = (0..400.min(n)).chain((400..n).step_by(7)).chain([n - 1]);
        for cut in cuts {
            let code = refusal(&format!("{ts} cut at {cut}/{n}"), &bytes[..cut]);
            assert!(
                matches!(
                    code,
                    "dicom_not_dicom"
                        | "dicom_parse_error"
                        | "dicom_missing_attribute"
                        | "dicom_no_pixel_data"
                        | "dicom_pixel_data_short"
                ),
                "{ts} cut at {cut}: {code}"
            );
        }
    }
}

#[test]
fn sequences_nested_a_hundred_thousand_deep_are_refused_without_recursing() {
    // Built as bytes: building such an object in memory would itself recurse.
    let mut obj = part10(ct(2, 2), EXPLICIT_LE);
    let at = find_tag(&obj, tags::PIXEL_DATA);
    let mut nest = Vec::new();
    for _ in 0..100_000 {
        // (0008,1115) Referenced Series Sequence, undefined length; an item of undefined length.
        nest.extend_from_slice(&[
            0x08, 0x00, 0x15, 0x11, b'S', b'Q', 0, 0, 0xFF, 0xFF, 0xFF, 0xFF,
        ]);
        nest.extend_from_slice(&[0xFE, 0xFF, 0x00, 0xE0, 0xFF, 0xFF, 0xFF, 0xFF]);
    }
    obj.splice(at..at, nest);
    let e = read("deep", &obj).expect_err("refused");
    assert_eq!(e.code(), "dicom_parse_error");
    assert!(e.to_string().contains("nests deeper than 32"), "{e}");
}

fn with(mut obj: InMemDicomObject, e: DataElement<InMemDicomObject>) -> InMemDicomObject {
    obj.put(e);
    obj
}

#[test]
fn absurd_frame_counts_and_sizes_are_refused_before_allocating() {
    for (frames, code) in [
        ("4294967295", "dicom_too_large"),
        ("99999999999999999999", "dicom_missing_attribute"),
        ("-3", "dicom_missing_attribute"),
        ("0", "dicom_missing_attribute"),
        ("two", "dicom_missing_attribute"),
        ("4096", "dicom_pixel_data_short"),
    ] {
        let obj = with(
            ct(8, 10),
            el(tags::NUMBER_OF_FRAMES, VR::IS, PrimitiveValue::from(frames)),
        );
        assert_eq!(
            refusal(frames, &part10(obj, EXPLICIT_LE)),
            code,
            "frames {frames}"
        );
    }
    // Rows × Columns × frames × samples × bytes overflows 64 bits under limits that allow every factor.
    let open = ReadLimits {
        max_side: u32::MAX,
        max_frames: u32::MAX,
        max_pixel_bytes: usize::MAX,
    };
    let obj = with(
        with(
            with(
                ct(8, 10),
                el(tags::ROWS, VR::US, dicom_value!(U16, [65535])),
            ),
            el(tags::COLUMNS, VR::US, dicom_value!(U16, [65535])),
        ),
        el(
            tags::NUMBER_OF_FRAMES,
            VR::IS,
            PrimitiveValue::from("2147483647"),
        ),
    );
    let obj = with(
        obj,
        el(tags::SAMPLES_PER_PIXEL, VR::US, dicom_value!(U16, [4])),
    );
    let e = read_with("overflow", &part10(obj, EXPLICIT_LE), &open).expect_err("refused");
    assert_eq!(e.code(), "dicom_too_large", "{e}");
}

#[test]
fn odd_bit_depths_are_refused_as_unsupported() {
    for (allocated, stored) in [
        (0u16, 0u16),
        (1, 1),
        (7, 7),
        (12, 12),
        (24, 24),
        (64, 64),
        (16, 17),
        (16, 0),
    ] {
        let obj = with(
            with(
                ct(8, 10),
                el(tags::BITS_ALLOCATED, VR::US, dicom_value!(U16, [allocated])),
            ),
            el(tags::BITS_STORED, VR::US, dicom_value!(U16, [stored])),
        );
        assert_eq!(
            refusal(
                &format!("{allocated}/{stored} bits"),
                &part10(obj, EXPLICIT_LE)
            ),
            "dicom_unsupported",
            "{allocated} allocated, {stored} stored"
        );
    }
}

#[test]
fn pixel_data_shorter_than_the_header_says_is_refused() {
    let obj = with(
        ct(8, 10),
        el(
            tags::PIXEL_DATA,
            VR::OW,
            PrimitiveValue::U16(vec![0; 8 * 10 - 1].into()),
        ),
    );
    assert_eq!(
        refusal("short pixels", &part10(obj, EXPLICIT_LE)),
        "dicom_pixel_data_short"
    );
}

#[test]
fn odd_and_undefined_lengths_where_not_allowed_are_refused_or_read_consistently() {
    let bytes = part10(ct(8, 10), EXPLICIT_LE);
    // Rows (US) declared 3 bytes long: the rest of the data set shifts by one byte.
    let mut odd = bytes.clone();
    let rows = find_tag(&odd, tags::ROWS);
    odd[rows + 6] = 3;
    let code = refusal("odd Rows length", &odd);
    assert!(code.starts_with("dicom_"), "{code}");
    // An undefined length on the meta group's version (OB), where the standard forbids one.
    let mut undefined = bytes.clone();
    let version = find_tag(&undefined, Tag(0x0002, 0x0001));
    undefined[version + 8..version + 12].copy_from_slice(&[0xFF; 4]);
    assert_eq!(
        refusal("undefined meta length", &undefined),
        "dicom_parse_error"
    );
    // An undefined length on a text element (UT) in the data set.
    let obj = with(
        ct(8, 10),
        el(tags::IMAGE_COMMENTS, VR::UT, PrimitiveValue::from("abcd")),
    );
    let mut text = part10(obj, EXPLICIT_LE);
    let c = find_tag(&text, tags::IMAGE_COMMENTS);
    text[c + 8..c + 12].copy_from_slice(&[0xFF; 4]);
    assert_eq!(refusal("undefined UT", &text), "dicom_parse_error");
}

// ---------------------------------------------------------------------------------------------------------
// Part 2: no length read from the input allocates more than the bytes that remain.

#[test]
fn a_uid_whose_vr_is_changed_to_an_unknown_one_allocates_nothing_like_its_false_length() {
    // The reported case: `UI` → an unknown VR makes the parser take 2 reserved bytes and a 4-byte length
    // made of the value's first bytes ("1.2." ≈ 0.8 GB).
    let mut bytes = part10(ct(32, 80), EXPLICIT_LE);
    assert!(bytes.len() > 5000, "{}", bytes.len());
    let uid = find_tag(&bytes, tags::SOP_INSTANCE_UID);
    assert_eq!(&bytes[uid + 4..uid + 6], b"UI");
    bytes[uid + 4..uid + 6].copy_from_slice(b"QQ");
    let e = read("UI → QQ", &bytes).expect_err("refused");
    assert_eq!(e.code(), "dicom_parse_error");
    assert!(e.to_string().contains("(0008,0018) declares"), "{e}");
}

#[test]
fn every_single_byte_corruption_of_the_header_stays_within_the_allocation_allowance() {
    for ts in [EXPLICIT_LE, IMPLICIT_LE] {
        let bytes = part10(ct(32, 80), ts);
        let pixels = find_tag(&bytes, tags::PIXEL_DATA) + 16;
        let (mut refused, mut read_ok) = (0, 0);
        for at in 128..pixels {
            for value in [0x00u8, 0xFF, 0x7F, b'Q'] {
                if bytes[at] == value {
                    continue;
                }
                let mut bad = bytes.clone();
                bad[at] = value;
                // `read` asserts no panic and the allocation bound.
                match read(&format!("{ts}: byte {at} = {value:#04x}"), &bad) {
                    Ok(_) => read_ok += 1,
                    Err(e) => {
                        assert!(e.code().starts_with("dicom_"), "{e}");
                        refused += 1;
                    }
                }
            }
        }
        // Both outcomes occur: corrupt lengths are refused, corrupt text values still read.
        assert!(
            refused > 100 && read_ok > 100,
            "{ts}: {refused} refused, {read_ok} read"
        );
    }
}

#[test]
fn hostile_npy_headers_are_refused_without_allocating_their_declared_size() {
    use ctrecon::storage::npy::decode_f32;
    let npy = |version: u8, dict: &str, data: usize| {
        let mut out = b"\x93NUMPY".to_vec();
        out.push(version);
        out.push(0);
        if version == 1 {
            out.extend_from_slice(&(dict.len() as u16).to_le_bytes());
        } else {
            out.extend_from_slice(&(dict.len() as u32).to_le_bytes());
        }
        out.extend_from_slice(dict.as_bytes());
        out.extend(std::iter::repeat_n(0u8, data));
        out
    };
    let cases = [
        // A shape of 2^62 elements with 64 bytes of data.
        npy(
            1,
            "{'descr': '<f4', 'fortran_order': False, 'shape': (4611686018427387904,), }\n",
            64,
        ),
        // A product that overflows 64 bits.
        npy(
            1,
            "{'descr': '<f8', 'fortran_order': False, 'shape': (4294967296, 4294967296, 16), }\n",
            64,
        ),
        // A zero dimension beside huge ones, and more data than it declares.
        npy(
            1,
            "{'descr': '<f4', 'fortran_order': False, 'shape': (0, 9223372036854775807), }\n",
            64,
        ),
    ];
    for (i, file) in cases.iter().enumerate() {
        let live0 = LIVE.with(|l| l.get());
        PEAK.with(|p| p.set(live0));
        let r = decode_f32(file);
        let peak = PEAK.with(|p| p.get()) - live0;
        assert!(r.is_err(), "case {i} decoded");
        assert!(peak < 64 << 10, "case {i}: peak {peak} bytes");
    }
    // A version 2 header that declares 4 GiB of header text in a 40-byte file.
    let mut huge = npy(2, "{}", 0);
    huge[8..12].copy_from_slice(&u32::MAX.to_le_bytes());
    let live0 = LIVE.with(|l| l.get());
    PEAK.with(|p| p.set(live0));
    assert!(decode_f32(&huge).is_err());
    assert!(PEAK.with(|p| p.get()) - live0 < 64 << 10);
}

#[test]
fn a_deflated_data_set_that_inflates_past_the_limit_is_refused_at_the_limit() {
    use std::io::Write;
    // Meta group naming Deflated Explicit VR Little Endian, then 80 MiB of zeros deflated (about 80 KiB).
    let ts = b"1.2.840.10008.1.2.1.99\0\0";
    let mut meta = vec![0x02, 0x00, 0x10, 0x00, b'U', b'I', ts.len() as u8, 0];
    meta.extend_from_slice(ts);
    let mut file = vec![0u8; 128];
    file.extend_from_slice(b"DICM");
    file.extend_from_slice(&[0x02, 0x00, 0x00, 0x00, b'U', b'L', 4, 0]);
    file.extend_from_slice(&(meta.len() as u32).to_le_bytes());
    file.extend_from_slice(&meta);
    let mut z = flate2::write::DeflateEncoder::new(file, flate2::Compression::fast());
    let zeros = vec![0u8; 1 << 20];
    for _ in 0..80 {
        z.write_all(&zeros).unwrap();
    }
    let bomb = z.finish().unwrap();
    assert!(bomb.len() < 1 << 20, "{}", bomb.len());
    let limits = ReadLimits {
        max_pixel_bytes: 1 << 20,
        ..ReadLimits::default()
    };
    // The limit is the pixel limit plus 64 MiB of attributes. The stream is measured before anything is
    // allocated for it: refusing it costs the inflater's own state (well under 1 MiB), not the limit.
    let e = read_within("deflate bomb", &bomb, &limits, 1 << 20).expect_err("refused");
    assert_eq!(e.code(), "dicom_parse_error");
    assert!(e.to_string().contains("inflates to more than"), "{e}");
}

/// A Part 10 file of `file` (explicit VR little endian) whose data set is deflated: the meta group with
/// Deflated Explicit VR Little Endian as its transfer syntax, then the data set as raw deflate.
fn deflated(file: &[u8]) -> Vec<u8> {
    use std::io::Write;
    let meta_len = u32::from_le_bytes(file[140..144].try_into().unwrap()) as usize;
    let (meta, data) = (&file[144..144 + meta_len], &file[144 + meta_len..]);
    let mut kept = Vec::new();
    let mut at = 0;
    while at < meta.len() {
        let tag = (
            u16::from_le_bytes([meta[at], meta[at + 1]]),
            u16::from_le_bytes([meta[at + 2], meta[at + 3]]),
        );
        let vr = &meta[at + 4..at + 6];
        let (head, len) = if matches!(vr, b"OB" | b"OW" | b"UN" | b"SQ" | b"UT") {
            (
                12,
                u32::from_le_bytes(meta[at + 8..at + 12].try_into().unwrap()) as usize,
            )
        } else {
            (8, u16::from_le_bytes([meta[at + 6], meta[at + 7]]) as usize)
        };
        if tag != (0x0002, 0x0010) {
            kept.extend_from_slice(&meta[at..at + head + len]);
        }
        at += head + len;
    }
    let ts = b"1.2.840.10008.1.2.1.99\0\0";
    kept.extend_from_slice(&[0x02, 0x00, 0x10, 0x00, b'U', b'I', ts.len() as u8, 0]);
    kept.extend_from_slice(ts);
    let mut out = vec![0u8; 128];
    out.extend_from_slice(b"DICM");
    out.extend_from_slice(&[0x02, 0x00, 0x00, 0x00, b'U', b'L', 4, 0]);
    out.extend_from_slice(&(kept.len() as u32).to_le_bytes());
    out.extend_from_slice(&kept);
    let mut z = flate2::write::DeflateEncoder::new(out, flate2::Compression::best());
    z.write_all(data).unwrap();
    z.finish().unwrap()
}

#[test]
fn a_small_deflated_file_of_smooth_pixels_reads_whatever_its_ratio_and_a_bomb_does_not() {
    use ctrecon::dicom::{SeriesMeta, header_of, write_ct_series};
    use ctrecon::volume::{Frame, Volume};
    // A 64 × 64 CT slice of one value: its data set deflates more than 20-fold.
    let vol = Volume {
        data: ndarray::Array3::from_elem((2, 64, 64), 40.0),
        frame: Frame {
            origin_mm: [0.0, 0.0, 0.0],
            spacing_mm: [1.0, 1.0, 2.0],
            direction: Frame::AXIS_ALIGNED,
        },
    };
    let series = write_ct_series(&vol, &SeriesMeta::default()).unwrap();
    let plain = &series.files[0].1;
    let small = deflated(plain);
    assert!(
        small.len() * 4 < plain.len(),
        "{} of {}",
        small.len(),
        plain.len()
    );
    let h = header_of("smooth", &small).expect("the header of a small deflated file");
    let want = header_of("plain", plain).unwrap();
    assert_eq!(
        (h.sop_instance_uid, h.series_uid, h.transfer_syntax),
        (
            want.sop_instance_uid,
            want.series_uid,
            "1.2.840.10008.1.2.1.99".to_string()
        )
    );
    assert_eq!(
        read_bytes("smooth", &small, &ReadLimits::default())
            .unwrap()
            .slices[0]
            .stored,
        read_bytes("plain", plain, &ReadLimits::default())
            .unwrap()
            .slices[0]
            .stored
    );
    // The same file with 80 MiB of zeros after its data set: a header read stops at its 16 MiB floor.
    let mut padded = plain.clone();
    padded.extend(std::iter::repeat_n(0u8, 80 << 20));
    let bomb = deflated(&padded);
    assert!(bomb.len() < 1 << 20, "{}", bomb.len());
    let e = header_of("bomb", &bomb).expect_err("refused");
    assert!(e.to_string().contains("inflates to more than"), "{e}");
}

// ---------------------------------------------------------------------------------------------------------
// Part 3: read what peers read.

fn pixels_of(inst: &Instance) -> Vec<f32> {
    inst.slices[0].stored.clone()
}

#[test]
fn zero_padding_after_the_data_set_is_ignored_with_a_warning() {
    let bytes = part10(ct(8, 10), EXPLICIT_LE);
    let want = pixels_of(&read("intact", &bytes).unwrap());
    for pad in [1usize, 5, 12, 13, 1000] {
        let mut padded = bytes.clone();
        padded.extend(std::iter::repeat_n(0u8, pad));
        let inst = read(&format!("{pad} zero bytes"), &padded).expect("read");
        assert_eq!(pixels_of(&inst), want);
        assert!(
            inst.warnings
                .iter()
                .any(|w| w.code == "trailing_bytes_ignored"),
            "{pad}: {:?}",
            inst.warnings
        );
    }
    // Data Set Trailing Padding (FFFC,FFFC) OB, as the standard spells it.
    let mut padded = bytes.clone();
    padded.extend_from_slice(&[0xFC, 0xFF, 0xFC, 0xFF, b'O', b'B', 0, 0, 6, 0, 0, 0]);
    padded.extend_from_slice(&[0xAA; 6]);
    let inst = read("trailing padding element", &padded).expect("read");
    assert_eq!(pixels_of(&inst), want);
}

#[test]
fn a_data_set_without_preamble_marker_or_meta_group_is_read_in_its_guessed_encoding() {
    for ts in [EXPLICIT_LE, IMPLICIT_LE] {
        let file = ct(8, 10)
            .with_meta(FileMetaTableBuilder::new().transfer_syntax(ts))
            .expect("meta");
        let mut raw = Vec::new();
        file.write_dataset(&mut raw).expect("write");
        let want = pixels_of(&read("intact", &part10(ct(8, 10), ts)).unwrap());
        let inst = read(&format!("raw {ts}"), &raw).expect("read");
        assert_eq!(inst.transfer_syntax, ts);
        assert_eq!(pixels_of(&inst), want);
        assert_eq!(inst.slices[0].position_mm, Some([-10.0, -20.0, 30.0]));
        assert!(
            inst.warnings
                .iter()
                .any(|w| w.code == "transfer_syntax_guessed")
        );
        // `DICM` and the meta group without the preamble: no guess needed.
        let mut marked = b"DICM".to_vec();
        marked.extend_from_slice(&part10(ct(8, 10), ts)[132..]);
        let inst = read(&format!("no preamble {ts}"), &marked).expect("read");
        assert_eq!(pixels_of(&inst), want);
        assert!(inst.warnings.is_empty(), "{:?}", inst.warnings);
    }
    // Bytes that open with no plausible element are still not DICOM.
    assert_eq!(
        refusal("text", b"hello, this is not a DICOM file at all"),
        "dicom_not_dicom"
    );
}

#[test]
fn a_meta_group_without_its_group_length_is_read() {
    let bytes = part10(ct(8, 10), EXPLICIT_LE);
    let want = pixels_of(&read("intact", &bytes).unwrap());
    // Drop (0002,0000) UL (12 bytes after DICM).
    assert_eq!(&bytes[132..134], &[0x02, 0x00]);
    assert_eq!(&bytes[134..136], &[0x00, 0x00]);
    let mut no_length = bytes[..132].to_vec();
    no_length.extend_from_slice(&bytes[144..]);
    let inst = read("no group length", &no_length).expect("read");
    assert_eq!(pixels_of(&inst), want);
}

/// `ct(rows, columns)` with its pixel data replaced by the JPEG-LS frames `frames` (one fragment each).
fn ct_jpeg_ls(rows: u16, columns: u16, frames: Vec<Vec<u8>>) -> InMemDicomObject {
    with(
        ct(rows, columns),
        DataElement::new(
            tags::PIXEL_DATA,
            VR::OB,
            dicom_core::value::Value::PixelSequence(dicom_core::value::PixelFragmentSequence::new(
                vec![],
                frames,
            )),
        ),
    )
}

/// The stored values of `ct(rows, columns)` as JPEG-LS codes them (16-bit two's complement words).
fn ct_words(rows: u16, columns: u16) -> Vec<u16> {
    (0..rows as i32)
        .flat_map(|r| (0..columns as i32).map(move |c| (100 * r + c - 500) as i16 as u16))
        .collect()
}

fn jls(words: &[u16], columns: u32, rows: u32, near: u8) -> Vec<u8> {
    let mut o = jpegls::EncodeOptions::default();
    o.near = near;
    o.precision = Some(16);
    let mut out = Vec::new();
    jpegls::encode_with_options(words, columns, rows, &o, &mut out).expect("encode");
    if out.len() % 2 == 1 {
        out.push(0); // fragments have even length
    }
    out
}

#[test]
fn jpeg_ls_decodes_exactly_and_bad_streams_are_decode_errors() {
    // Lossless: the same HU as the uncompressed file.
    let plain = read("plain", &part10(ct(8, 10), EXPLICIT_LE)).expect("plain");
    let frame = jls(&ct_words(8, 10), 10, 8, 0);
    let lossless = read(
        "jpeg-ls",
        &part10(
            ct_jpeg_ls(8, 10, vec![frame.clone()]),
            "1.2.840.10008.1.2.4.80",
        ),
    )
    .expect("JPEG-LS lossless is read");
    assert_eq!(pixels_of(&lossless), pixels_of(&plain));
    // Near-lossless (NEAR = 2 on the 16-bit words): within 2 of the truth.
    let near = jls(&ct_words(8, 10), 10, 8, 2);
    let got = read(
        "jpeg-ls near",
        &part10(ct_jpeg_ls(8, 10, vec![near]), "1.2.840.10008.1.2.4.81"),
    )
    .expect("near-lossless is read");
    let worst = pixels_of(&got)
        .iter()
        .zip(pixels_of(&plain))
        .map(|(a, b)| (a - b).abs())
        .fold(0.0f32, f32::max);
    assert!(worst <= 2.0, "near-lossless error {worst}");

    // A frame of another size, a stream cut short, and garbage after SOI are decode errors.
    let other_size = jls(&ct_words(8, 9), 9, 8, 0);
    let mut cut = frame.clone();
    cut.truncate(frame.len() / 2);
    for (what, bad) in [
        ("other size", other_size),
        ("cut", cut),
        (
            "garbage",
            vec![0xFF, 0xD8, 0xFF, 0xF7, 0, 0, 0, 0, 0xFF, 0xD9],
        ),
    ] {
        for ts in ["1.2.840.10008.1.2.4.80", "1.2.840.10008.1.2.4.81"] {
            let bytes = part10(ct_jpeg_ls(8, 10, vec![bad.clone()]), ts);
            assert_eq!(refusal(what, &bytes), "dicom_decode_error", "{what} {ts}");
        }
    }
}

#[test]
fn unregistered_transfer_syntaxes_are_refused_with_their_own_code() {
    // A transfer syntax nobody registered.
    let e = read("unknown ts", &unknown_ts()).expect_err("refused");
    assert_eq!(e.code(), "dicom_unsupported_transfer_syntax", "{e}");
}

// ---------------------------------------------------------------------------------------------------------
// Part 4: silent defaults become warnings.

#[test]
fn a_ct_without_rescale_or_series_uid_says_what_it_assumed() {
    let mut obj = ct(8, 10);
    obj.remove_element(tags::RESCALE_SLOPE);
    obj.remove_element(tags::RESCALE_INTERCEPT);
    obj.put(el(
        tags::SERIES_INSTANCE_UID,
        VR::UI,
        PrimitiveValue::from(""),
    ));
    let inst = read("defaults", &part10(obj, EXPLICIT_LE)).expect("read");
    assert_eq!(
        (
            inst.slices[0].rescale_slope,
            inst.slices[0].rescale_intercept
        ),
        (1.0, 0.0)
    );
    let codes: Vec<&str> = inst.warnings.iter().map(|w| w.code).collect();
    assert!(codes.contains(&"rescale_assumed"), "{codes:?}");
    assert!(codes.contains(&"series_uid_missing"), "{codes:?}");
    // The intact file has neither.
    let inst = read("intact", &part10(ct(8, 10), EXPLICIT_LE)).expect("read");
    assert!(inst.warnings.is_empty(), "{:?}", inst.warnings);
}

// ---------------------------------------------------------------------------------------------------------
// Through the real server: hostile files are 422 problems with their code, never a 500.

async fn post_dicom(app: &common::TestApp, body: Vec<u8>) -> reqwest::Response {
    app.client
        .post(app.url("/v1/series"))
        .header("content-type", "application/dicom")
        .body(body)
        .send()
        .await
        .expect("request")
}

#[tokio::test]
async fn the_service_answers_hostile_files_with_their_codes() {
    let app = common::spawn_app().await;
    let bytes = part10(ct(32, 80), EXPLICIT_LE);
    // The meta group cut short: once a 500.
    common::assert_problem(
        post_dicom(&app, bytes[..150].to_vec()).await,
        422,
        "dicom_parse_error",
    )
    .await;
    let mut qq = bytes.clone();
    let uid = find_tag(&qq, tags::SOP_INSTANCE_UID);
    qq[uid + 4..uid + 6].copy_from_slice(b"QQ");
    let p = common::assert_problem(post_dicom(&app, qq).await, 422, "dicom_parse_error").await;
    assert!(
        p["detail"]
            .as_str()
            .unwrap()
            .contains("(0008,0018) declares"),
        "{p}"
    );
    let jls = unknown_ts();
    common::assert_problem(
        post_dicom(&app, jls).await,
        422,
        "dicom_unsupported_transfer_syntax",
    )
    .await;
    // A raw data set (no preamble, marker or meta group) opens an upload.
    let file = ct(8, 10)
        .with_meta(FileMetaTableBuilder::new().transfer_syntax(IMPLICIT_LE))
        .expect("meta");
    let mut raw = Vec::new();
    file.write_dataset(&mut raw).expect("write");
    assert_eq!(post_dicom(&app, raw).await.status(), 201);
}

#[test]
fn palette_and_rgb_images_are_refused_as_volumes_with_their_own_code() {
    use ctrecon::dicom::read_upload;
    use ctrecon::recon::control::unattended;
    use ctrecon::series::AssemblyOptions;
    let palette = with(
        ct(8, 10),
        el(
            tags::PHOTOMETRIC_INTERPRETATION,
            VR::CS,
            PrimitiveValue::from("PALETTE COLOR"),
        ),
    );
    let rgb = with(
        with(
            with(
                with(
                    ct(8, 10),
                    el(
                        tags::PHOTOMETRIC_INTERPRETATION,
                        VR::CS,
                        PrimitiveValue::from("RGB"),
                    ),
                ),
                el(tags::SAMPLES_PER_PIXEL, VR::US, dicom_value!(U16, [3])),
            ),
            el(tags::PLANAR_CONFIGURATION, VR::US, dicom_value!(U16, [0])),
        ),
        el(
            tags::PIXEL_DATA,
            VR::OW,
            PrimitiveValue::U16(vec![7; 8 * 10 * 3].into()),
        ),
    );
    for (name, obj, photometric) in [("palette", palette, "PALETTE COLOR"), ("rgb", rgb, "RGB")] {
        let files = vec![(format!("{name}.dcm"), part10(obj, EXPLICIT_LE))];
        let up = read_upload(&files, &ReadLimits::default(), unattended()).expect("read");
        assert!(up.rejected.is_empty(), "{:?}", up.rejected);
        let group = up.series.into_iter().next().expect("a series");
        let e = group
            .assemble(&AssemblyOptions::default(), true, unattended())
            .expect_err("refused");
        assert_eq!(e.code(), "dicom_unsupported_photometric", "{e}");
        assert!(
            e.to_string().contains(photometric) && e.to_string().contains(name),
            "{e}"
        );
    }
}

// ---------------------------------------------------------------------------------------------------------
// Fuzz regressions: every input kept under tests/fuzz-regressions/TARGET goes through the fuzz target's own
// entry point and must return without a panic; the `valid-*` seeds must still read.

fn regression_inputs(target: &str) -> Vec<(String, Vec<u8>)> {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/fuzz-regressions")
        .join(target);
    let mut out: Vec<(String, Vec<u8>)> = std::fs::read_dir(&dir)
        .expect("regression folder")
        .map(|e| {
            let p = e.expect("entry").path();
            let name = p.file_name().unwrap().to_string_lossy().into_owned();
            (name, std::fs::read(&p).expect("read"))
        })
        .collect();
    out.sort();
    out
}

fn replay(target: &str, entry: fn(&[u8])) -> usize {
    count_panics();
    let inputs = regression_inputs(target);
    for (name, bytes) in &inputs {
        let panics0 = PANICS.with(|p| p.get());
        let r = std::panic::catch_unwind(|| entry(bytes));
        let panics = PANICS.with(|p| p.get()) - panics0;
        assert!(r.is_ok() && panics == 0, "{target}/{name}: panicked");
    }
    inputs.len()
}

#[test]
fn fuzz_regression_inputs_replay_without_panics() {
    assert!(replay("dicom_read", ctrecon::dicom::fuzz_entry) >= 7);
    assert!(replay("npy_read", ctrecon::storage::npy::fuzz_entry) >= 4);
    for (name, bytes) in regression_inputs("dicom_read") {
        let r = read(&name, &bytes);
        assert_eq!(
            r.is_ok(),
            name.starts_with("valid-") || name.starts_with("trailing-") || name.starts_with("raw-"),
            "{name}: {:?}",
            r.err()
        );
    }
    for (name, bytes) in regression_inputs("npy_read") {
        let r = ctrecon::storage::npy::decode_f32(&bytes);
        assert_eq!(
            r.is_ok(),
            name.starts_with("valid-"),
            "{name}: {:?}",
            r.err()
        );
    }
}

#[test]
fn a_binary_value_that_is_not_a_whole_number_of_values_is_refused_before_the_parser_desyncs() {
    // Found by fuzzing: High Bit (0028,0102) as FD with 2 bytes. dicom-rs reads no value but counts 2 bytes,
    // then reads an OB length out of the JPEG stream and reserved 555 MB for it.
    let dir =
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fuzz-regressions/dicom_read");
    let bytes =
        std::fs::read(dir.join("high-bit-fd-of-2-bytes-desyncs-the-parser.dcm")).expect("read");
    let e = read("fd-2-bytes", &bytes).expect_err("refused");
    assert_eq!(e.code(), "dicom_parse_error", "{e}");
    assert!(
        e.to_string().contains("(0028,0102) FD declares 2 bytes"),
        "{e}"
    );
    // The neighbour: a US value of 3 bytes in an otherwise valid file.
    let valid = std::fs::read(dir.join("valid-4x4-explicit.dcm")).expect("read");
    let at = valid
        .windows(8)
        .position(|w| w == [0x28, 0x00, 0x00, 0x01, b'U', b'S', 2, 0])
        .expect("Bits Allocated");
    let mut odd = valid.clone();
    odd[at + 6] = 3;
    odd.insert(at + 8, 0);
    let e = read("us-3-bytes", &odd).expect_err("refused");
    assert_eq!(e.code(), "dicom_parse_error", "{e}");
    assert!(
        e.to_string()
            .contains("(0028,0100) US declares 3 bytes, not a multiple of its 2-byte values"),
        "{e}"
    );
    assert!(read("valid", &valid).is_ok());
}

#[test]
fn a_jpeg_frame_header_that_differs_from_the_image_is_refused_before_decoding() {
    // Found by fuzzing: a 256×256 RGB image whose JPEG frame header says 768×256. dicom-rs sized its buffer
    // from the DICOM header and copied the larger decoded frame past its end (a panic).
    let dir =
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fuzz-regressions/dicom_read");
    let bytes =
        std::fs::read(dir.join("jpeg-frame-768-rows-in-a-256-row-image.dcm")).expect("read");
    let e = read("jpeg-768", &bytes).expect_err("refused");
    assert_eq!(e.code(), "dicom_decode_error", "{e}");
    assert!(
        e.to_string()
            .contains("declares 768×256 pixels × 3 components"),
        "{e}"
    );
}

#[test]
fn a_jpeg_ls_stream_that_overflows_the_decoder_statistics_is_a_decode_error() {
    // Found by fuzzing: a mutated JPEG-LS frame whose prediction errors overflow the decoder's context
    // statistics (a 32-bit add in the third-party codec). The codec runs contained: the file is refused with a
    // decode problem, the request and the job go on.
    let dir =
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fuzz-regressions/dicom_read");
    let bytes = std::fs::read(dir.join("jpeg-ls-context-statistics-overflow.dcm")).expect("read");
    let e = read("jpeg-ls-overflow", &bytes).expect_err("refused");
    assert_eq!(e.code(), "dicom_decode_error", "{e}");
    assert!(
        e.to_string()
            .contains("the JPEG-LS decoder failed on malformed data"),
        "{e}"
    );
    assert!(!ctrecon::dicom::panic_is_contained());
}

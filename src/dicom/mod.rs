//! DICOM: the only module that imports dicom-rs — reading CT series and writing derived results.
//!
//! - [`read_bytes`] / [`read_path`]: one Part 10 file into an [`Instance`] whose frames are
//!   [`crate::series::Slice`]s (stored values plus placement and rescale); native, deflated and the compressed transfer
//!   syntaxes dicom-pixeldata decodes (JPEG baseline/extended/lossless, RLE, JPEG 2000), JPEG-LS and 12-bit JPEG
//!   Extended (decoded here), implicit VR and big endian,
//!   multi-frame Enhanced CT with functional groups, signed/unsigned pixels and pixel padding.
//! - [`unpack`]: an upload body (a single file or a ZIP, with bomb limits; names inside the ZIP are labels,
//!   never paths) into named byte buffers; [`read_upload`] decodes them in parallel and splits them by
//!   SeriesInstanceUID into [`SeriesGroup`]s, each with a [`SeriesReport`] and [`SeriesGroup::assemble`].
//! - [`declared`]: what a file's pixels will cost once decoded, from its header alone (reserved before
//!   decoding, so that compressed input cannot escape the memory budget).
//! - [`unpack_file`] / [`read_upload_files`]: the same from files on disk, ZIP members inflated one by one
//!   into a scratch directory and refused one by one (what the service uses: nothing is held whole).
//! - Writers: [`write_ct_series`] (a volume as a derived CT series), [`write_enhanced_ct`] (one multi-frame
//!   file), [`write_secondary_capture`] (a 2D image), [`write_secondary_capture_rgb`] (rendered RGB frames), [`write_encapsulated_stl`] and [`write_zip`].
//!
//! - [`instance_json`] / [`explicit_le_bytes`]: a stored instance in the DICOM JSON model, and in explicit
//!   VR little endian with native pixel data, compressed ones decoded by the reader's decoders (DICOMweb);
//!   [`multipart`]: streamed `multipart/related` bodies (pure).
//! - [`is_valid_uid`] / [`check_uid`]: the UID check every door applies to what it receives (PS3.5 §9.1), the
//!   refusal ([`DicomError::InvalidUid`]) showing a hostile value only shortened and escaped.
//! - [`read_identifier`] / [`write_identifier`]: the data sets of C-FIND and C-MOVE requests and responses.
//! - [`data_set_as`]: a stored data set re-encoded between explicit and implicit VR little endian (C-STORE to
//!   a peer that accepted only the other).
//!
//! Every failure is a [`DicomError`] with a stable [`DicomError::code`].

mod contain;
mod declared;
mod decompress;
mod error;
mod framing;
mod fuzz;
mod header;
mod identifier;
mod jpeg;
mod jpeg12;
mod jpeg_ls;
pub mod multipart;
mod pixels;
mod read;
mod scan;
mod transcode;
mod uid;
mod unzip;
mod upload;
mod web;
mod write;

pub use contain::panic_is_contained;
pub use declared::{Declared, MAX_LEADING_BYTES, declared};
pub use decompress::{explicit_le_bytes, transcodable_to_explicit_le};
pub use error::DicomError;
#[doc(hidden)]
pub use fuzz::fuzz_zip_entry;
pub use header::{
    IMPLEMENTATION_CLASS_UID, IMPLEMENTATION_VERSION, InstanceHeader, Part10, STORABLE_SOP_CLASSES,
    decodable_transfer_syntaxes, header_of, part10_prefix, read_bounded, read_header, read_part10,
};
pub use identifier::{IdentifierElement, MAX_IDENTIFIER_BYTES, read_identifier, write_identifier};
pub use read::{Instance, ReadLimits, fuzz_entry, read_bytes, read_path};
pub use transcode::{data_set_as, le_interchangeable};
pub use uid::{MAX_UID_CHARS, check_uid, is_valid_uid, uid_defect, value_summary};
pub use unzip::{
    Unpacked, UploadFile, is_zip, read_upload_file, read_upload_files, starts_like, unpack_file,
};
pub use upload::{
    Rejected, SeriesGroup, SeriesReport, Upload, ZipLimits, group_series, read_upload, unpack,
};
pub use web::{EXPLICIT_LE, IMPLICIT_LE, MAX_INLINE_BINARY, instance_json};
pub use write::{
    DerivedSeries, RgbFrames, ScOrientation, SeriesMeta, new_uid, write_ct_series,
    write_encapsulated_stl, write_enhanced_ct, write_secondary_capture,
    write_secondary_capture_frame, write_secondary_capture_placed, write_secondary_capture_rgb,
    write_zip,
};

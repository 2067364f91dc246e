//! What WADO-RS sends of a stored instance beside its file as it is: the file in explicit VR little endian
//! (compressed pixel data decoded) unless the retrieval asks for the stored syntax, its attributes in the
//! DICOM JSON model (`/metadata`), and a frame rendered to PNG or JPEG through a window, fitted to a
//! viewport (`/rendered`). Decoding and encoding run on the engine's pool, never on the async threads.

use ndarray::Array2;
use serde_json::Value;

use super::{App, AppResult};
use crate::dicom::{
    EXPLICIT_LE, ReadLimits, explicit_le_bytes, instance_json, read_path,
    transcodable_to_explicit_le,
};
use crate::error_code::{ErrorCode, Problem};
use crate::jobs::model::StoredInstance;
use crate::jobs::views::volume_problem;
use crate::volume::{BitDepth, Window, encode_jpeg, encode_png, fit_viewport};

/// A window asked for by `window=center,width,function` (PS3.18 §8.3.5.1.3): only `linear` is offered.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RenderWindow {
    pub center: f64,
    pub width: f64,
}

impl RenderWindow {
    /// Parse `center,width[,linear]`.
    pub fn parse(s: &str) -> Result<RenderWindow, Problem> {
        let bad = |d: &str| Problem::new(ErrorCode::InvalidQuery, d.to_string());
        let parts: Vec<&str> = s.split(',').map(str::trim).collect();
        if !(parts.len() == 2 || parts.len() == 3) {
            return Err(bad("window is center,width,function"));
        }
        if parts.len() == 3 && !parts[2].eq_ignore_ascii_case("linear") {
            return Err(bad("only the linear window function is offered"));
        }
        let num = |v: &str| v.parse::<f64>().ok().filter(|x| x.is_finite());
        match (num(parts[0]), num(parts[1])) {
            (Some(center), Some(width)) if width > 0.0 => Ok(RenderWindow { center, width }),
            _ => Err(bad(
                "window center and width must be finite numbers, the width positive",
            )),
        }
    }
}

/// The media type of a rendered frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum RenderedMedia {
    /// `image/png`, 8-bit greyscale.
    Png,
    /// `image/jpeg`, 8-bit greyscale baseline, at `quality` 1–100.
    Jpeg { quality: u8 },
}

/// The quality of a rendered JPEG when the request names none.
pub const DEFAULT_JPEG_QUALITY: u8 = 90;

impl RenderedMedia {
    pub fn content_type(self) -> &'static str {
        match self {
            RenderedMedia::Png => "image/png",
            RenderedMedia::Jpeg { .. } => "image/jpeg",
        }
    }
}

/// Parse `quality` (PS3.18 §8.3.5.1.2): an integer from 1 to 100.
pub fn parse_quality(s: &str) -> Result<u8, Problem> {
    s.trim()
        .parse::<u8>()
        .ok()
        .filter(|q| (1..=100).contains(q))
        .ok_or_else(|| {
            Problem::new(
                ErrorCode::InvalidQuery,
                "quality is an integer from 1 to 100",
            )
        })
}

/// The viewport of a rendering (PS3.18 §8.3.5.1.4): `vw,vh`, the picture scaled to fit it with its aspect
/// ratio kept. The source-region form (`vw,vh,sx,sy,sw,sh`) is not offered.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Viewport {
    pub columns: usize,
    pub rows: usize,
}

impl Viewport {
    pub fn parse(s: &str) -> Result<Viewport, Problem> {
        let bad = |d: &str| Problem::new(ErrorCode::InvalidQuery, d.to_string());
        let parts: Vec<&str> = s.split(',').map(str::trim).collect();
        if parts.len() != 2 {
            return Err(bad(
                "viewport is vw,vh (the source-region form vw,vh,sx,sy,sw,sh is not offered)",
            ));
        }
        let side = |v: &str| {
            v.parse::<usize>()
                .ok()
                .filter(|n| (1..=crate::volume::MAX_VIEWPORT_SIDE).contains(n))
        };
        match (side(parts[0]), side(parts[1])) {
            (Some(columns), Some(rows)) => Ok(Viewport { columns, rows }),
            _ => Err(bad(&format!(
                "viewport width and height are integers from 1 to {}",
                crate::volume::MAX_VIEWPORT_SIDE
            ))),
        }
    }
}

/// How a frame is rendered: media type, window and viewport.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Rendering {
    pub media: RenderedMedia,
    /// `None`: a window spanning the frame's values.
    pub window: Option<RenderWindow>,
    pub viewport: Option<Viewport>,
}

/// The transfer syntax each instance of a retrieval is sent in.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum RetrieveSyntax {
    /// As stored (`transfer-syntax=*`).
    Stored,
    /// Explicit VR little endian, compressed pixel data decoded (`transfer-syntax=1.2.840.10008.1.2.1`, and
    /// the PS3.18 default of `application/dicom` when no syntax is named).
    ExplicitLe,
}

impl RetrieveSyntax {
    /// Whether an instance stored in `ts` is re-encoded.
    fn transcodes(self, ts: &str) -> bool {
        match self {
            RetrieveSyntax::Stored => false,
            RetrieveSyntax::ExplicitLe => ts != EXPLICIT_LE,
        }
    }

    /// Refuse (`not_acceptable`) a retrieval in explicit VR little endian of instances stored in a syntax
    /// the reader does not decode, naming the first.
    pub fn check(self, instances: &[StoredInstance]) -> Result<(), Problem> {
        if self != RetrieveSyntax::ExplicitLe {
            return Ok(());
        }
        match instances
            .iter()
            .find(|i| !transcodable_to_explicit_le(&i.instance.transfer_syntax))
        {
            Some(i) => Err(Problem::new(
                ErrorCode::NotAcceptable,
                format!(
                    "instance {} is stored in {}, which is not decoded here: ask for transfer-syntax=*",
                    i.instance.sop_instance_uid, i.instance.transfer_syntax
                ),
            )),
            None => Ok(()),
        }
    }
}

impl App {
    /// The bytes and the transfer syntax the stored instance `i` is retrieved with in `syntax`: `None` when
    /// its file is sent as it is (streamed by the caller).
    pub async fn retrieved_instance(
        &self,
        i: &StoredInstance,
        syntax: RetrieveSyntax,
    ) -> AppResult<(Option<Vec<u8>>, String)> {
        let ts = i.instance.transfer_syntax.as_str();
        if syntax.transcodes(ts) {
            Ok((
                Some(self.instance_explicit_le(i).await?),
                EXPLICIT_LE.into(),
            ))
        } else {
            Ok((None, ts.to_string()))
        }
    }

    fn instance_limit(&self) -> u64 {
        self.settings
            .dicom
            .max_instance_bytes
            .saturating_add(64 << 10)
    }

    /// The stored instance `i` as a Part 10 file in explicit VR little endian, its pixel data decoded when
    /// it is stored compressed (one instance in memory at a time: the decoded pixels are held in the
    /// engine's memory budget while they exist).
    pub async fn instance_explicit_le(&self, i: &StoredInstance) -> AppResult<Vec<u8>> {
        let (path, max) = (self.instance_file(i), self.instance_limit());
        // Decoding, and the answer: the file with its pixels decoded.
        let _held = self
            .reserve_decoding(path.clone(), &i.instance.sop_instance_uid, |d| {
                d.file_bytes.saturating_add(d.decoded_bytes)
            })
            .await?;
        Ok(self
            .engine
            .compute(move || {
                explicit_le_bytes(&path, max, &ReadLimits::default()).map_err(|e| {
                    Problem::new(
                        ErrorCode::NotAcceptable,
                        format!("cannot be sent in explicit VR little endian: {e}"),
                    )
                })
            })
            .await?)
    }

    /// The DICOM JSON model of the stored instance `i`.
    pub async fn instance_metadata(&self, i: &StoredInstance) -> AppResult<Value> {
        let (path, max) = (self.instance_file(i), self.instance_limit());
        Ok(self
            .engine
            .compute(move || {
                instance_json(&path, max).map_err(|e| {
                    tracing::error!(error = %e, "a stored instance cannot be read");
                    Problem::internal()
                })
            })
            .await?)
    }

    /// Frame `frame` (1-based) of the stored instance `i` rendered as `how` says: Hounsfield units (stored
    /// values after the rescale) through its window, or a window spanning the frame's values when none is
    /// given, fitted to its viewport, as an 8-bit greyscale PNG or JPEG.
    pub async fn render_instance(
        &self,
        i: &StoredInstance,
        frame: usize,
        how: Rendering,
    ) -> AppResult<Vec<u8>> {
        let path = self.instance_file(i);
        // Decoding, and the frame in HU with its viewport.
        let _held = self
            .reserve_decoding(path.clone(), &i.instance.sop_instance_uid, |d| {
                d.kept_bytes().saturating_mul(2)
            })
            .await?;
        Ok(self
            .engine
            .compute(move || {
                let inst = read_path(&path, &ReadLimits::default())
                    .map_err(|e| crate::jobs::ingest::dicom_problem(&e))?;
                let n = inst.slices.len();
                let slice = frame
                    .checked_sub(1)
                    .and_then(|k| inst.slices.get(k))
                    .ok_or_else(|| {
                        Problem::new(
                            ErrorCode::DicomwebNotFound,
                            format!("frame {frame} is not among the instance's {n} frames"),
                        )
                    })?;
                let samples = slice.stored.len() / (slice.rows * slice.columns).max(1);
                if samples != 1 {
                    return Err(Problem::new(
                        ErrorCode::NotAcceptable,
                        "only grey images are rendered",
                    ));
                }
                let mut hu = Array2::from_shape_fn((slice.rows, slice.columns), |(r, c)| {
                    (slice.stored[r * slice.columns + c] as f64 * slice.rescale_slope
                        + slice.rescale_intercept) as f32
                });
                let w = match how.window {
                    Some(w) => Window::new(w.width, w.center).map_err(|e| volume_problem(&e))?,
                    None => Window::auto(hu.view()),
                };
                if let Some(v) = how.viewport {
                    hu = fit_viewport(hu.view(), v.rows, v.columns)
                        .map_err(|e| volume_problem(&e))?;
                }
                match how.media {
                    RenderedMedia::Png => encode_png(hu.view(), w, BitDepth::Eight),
                    RenderedMedia::Jpeg { quality } => encode_jpeg(hu.view(), w, quality),
                }
                .map_err(|e| volume_problem(&e))
            })
            .await?)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn quality_and_viewport_are_parsed_as_ps3_18_defines_them() {
        assert_eq!(parse_quality("90").unwrap(), 90);
        assert_eq!(parse_quality("1").unwrap(), 1);
        assert_eq!(parse_quality("100").unwrap(), 100);
        for bad in ["0", "101", "-5", "9.5", "high", ""] {
            assert!(parse_quality(bad).is_err(), "{bad}");
        }
        assert_eq!(
            Viewport::parse("256, 128").unwrap(),
            Viewport {
                columns: 256,
                rows: 128
            }
        );
        for bad in ["256", "0,10", "10,-1", "a,b", "10,10,0,0,5,5", "99999,10"] {
            assert!(Viewport::parse(bad).is_err(), "{bad}");
        }
    }

    #[test]
    fn windows_are_center_width_and_linear() {
        assert_eq!(
            RenderWindow::parse("40,400").unwrap(),
            RenderWindow {
                center: 40.0,
                width: 400.0
            }
        );
        assert!(RenderWindow::parse("-600, 1500, LINEAR").is_ok());
        for bad in [
            "40",
            "40,0",
            "40,-1",
            "a,b",
            "40,400,sigmoid",
            "1,2,3,4",
            "NaN,1",
        ] {
            assert!(RenderWindow::parse(bad).is_err(), "{bad}");
        }
    }
}

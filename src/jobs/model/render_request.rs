//! The request specs of the rendering products (`volume_render`, `surface_render`) of a volume job, their
//! defaults and limits, and the conversion of their values into the volume's units. Model types only: the
//! checks at submission and the execution are in [`crate::jobs::render_products`].

use serde::{Deserialize, Serialize};

use super::result::VolumeUnits;
use crate::render::{
    Camera, Clip, Preset, RenderError, Shading, SsdOptions, Surface, TransferFunction, VrOptions,
};

/// Units of transfer-function values and iso-values in a request.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ValueUnits {
    /// Hounsfield units (μ volumes convert through the configured μ_water, `mu_water_per_mm`: μ = μ_water (1 +
    /// HU/1000)).
    #[default]
    Hu,
    /// The volume's own units.
    Native,
}

fn default_size() -> [usize; 2] {
    [512, 512]
}
fn one() -> usize {
    1
}
fn default_depth_cue() -> f64 {
    0.4
}

/// `{"type": "volume_render", "preset": "bone", "camera": {"view": "anterior"}, "size": [512, 512]}`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct VolumeRenderSpec {
    /// A built-in transfer function (default `bone` when no `transfer_function` is given).
    #[serde(default)]
    pub preset: Option<Preset>,
    #[serde(default)]
    pub transfer_function: Option<TransferFunction>,
    /// Units of the `transfer_function` values (presets are always HU).
    #[serde(default)]
    pub units: ValueUnits,
    #[serde(default)]
    pub camera: Camera,
    /// `[width, height]` in pixels.
    #[serde(default = "default_size")]
    pub size: [usize; 2],
    #[serde(default)]
    pub shading: Shading,
    #[serde(default)]
    pub clip: Clip,
    #[serde(default)]
    pub background: [f64; 3],
    /// Frames of a rotating sequence (1: a single picture).
    #[serde(default = "one")]
    pub frames: usize,
    #[serde(default)]
    pub step_mm: Option<f64>,
}

/// `{"type": "surface_render", "surfaces": [{"iso": -500, "color": [0.9, 0.7, 0.6], "opacity": 0.3},
/// {"iso": 300}], "camera": {"view": "left"}}`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SurfaceRenderSpec {
    pub surfaces: Vec<Surface>,
    /// Units of the iso-values.
    #[serde(default)]
    pub units: ValueUnits,
    #[serde(default)]
    pub camera: Camera,
    #[serde(default = "default_size")]
    pub size: [usize; 2],
    #[serde(default)]
    pub shading: Shading,
    #[serde(default = "default_depth_cue")]
    pub depth_cue: f64,
    #[serde(default)]
    pub clip: Clip,
    #[serde(default)]
    pub background: [f64; 3],
    #[serde(default = "one")]
    pub frames: usize,
    #[serde(default)]
    pub step_mm: Option<f64>,
}

/// Largest number of frames of a rotating rendering.
pub const MAX_RENDER_FRAMES: usize = 360;

/// A rendering product, either kind.
#[derive(Debug, Clone, PartialEq)]
pub enum RenderSpec {
    Volume(VolumeRenderSpec),
    Surface(SurfaceRenderSpec),
}

impl RenderSpec {
    pub(crate) fn camera(&self) -> &Camera {
        match self {
            RenderSpec::Volume(s) => &s.camera,
            RenderSpec::Surface(s) => &s.camera,
        }
    }
    pub(crate) fn size(&self) -> [usize; 2] {
        match self {
            RenderSpec::Volume(s) => s.size,
            RenderSpec::Surface(s) => s.size,
        }
    }
    pub(crate) fn frames(&self) -> usize {
        match self {
            RenderSpec::Volume(s) => s.frames,
            RenderSpec::Surface(s) => s.frames,
        }
    }
    pub fn kind(&self) -> &'static str {
        match self {
            RenderSpec::Volume(_) => "volume_render",
            RenderSpec::Surface(_) => "surface_render",
        }
    }
    /// The camera of frame `k`.
    pub(crate) fn camera_of(&self, k: usize) -> Camera {
        let mut c = *self.camera();
        c.azimuth_deg += 360.0 * k as f64 / self.frames().max(1) as f64;
        c
    }

    /// VR options with values in the volume's units (HU → μ through `mu_water`, /mm).
    pub(crate) fn vr(
        s: &VolumeRenderSpec,
        units: VolumeUnits,
        mu_water: f64,
    ) -> Result<VrOptions, RenderError> {
        let (tf, tf_units) = match (&s.transfer_function, s.preset) {
            (Some(_), Some(_)) => {
                return Err(RenderError::InvalidParameter {
                    name: "preset",
                    reason: "give either `preset` or `transfer_function`, not both".into(),
                });
            }
            (Some(tf), None) => (tf.clone(), s.units),
            (None, p) => (
                p.unwrap_or(Preset::Bone).transfer_function(),
                ValueUnits::Hu,
            ),
        };
        tf.validate()?;
        Ok(VrOptions {
            transfer_function: tf.map_values(|v| to_volume_units(v, tf_units, units, mu_water)),
            shading: s.shading,
            clip: s.clip.clone(),
            background: s.background,
            step_mm: s.step_mm,
        })
    }

    /// SSD options with iso-values in the volume's units (HU → μ through `mu_water`, /mm).
    pub(crate) fn ssd(s: &SurfaceRenderSpec, units: VolumeUnits, mu_water: f64) -> SsdOptions {
        SsdOptions {
            surfaces: s
                .surfaces
                .iter()
                .map(|sf| Surface {
                    iso: to_volume_units(sf.iso, s.units, units, mu_water),
                    ..*sf
                })
                .collect(),
            shading: s.shading,
            depth_cue: s.depth_cue,
            clip: s.clip.clone(),
            background: s.background,
            step_mm: s.step_mm,
        }
    }

    /// What the picture shows, for labels and DICOM DerivationDescription.
    pub fn describe(&self) -> String {
        let cam = self.camera();
        let what = match self {
            RenderSpec::Volume(s) => match (&s.transfer_function, s.preset) {
                (Some(tf), _) => format!(
                    "volume rendering, custom transfer function of {} points",
                    tf.points.len()
                ),
                (None, p) => format!(
                    "volume rendering, preset {}",
                    p.unwrap_or(Preset::Bone).name()
                ),
            },
            RenderSpec::Surface(s) => {
                let isos: Vec<String> = s
                    .surfaces
                    .iter()
                    .map(|sf| format!("{} at opacity {}", sf.iso, sf.opacity))
                    .collect();
                format!("shaded surface display, iso {}", isos.join(", "))
            }
        };
        let projection = match cam.projection {
            crate::render::Projection::Orthographic => "orthographic",
            crate::render::Projection::Perspective => "perspective",
        };
        format!(
            "ctrecon {what}; camera {} view, azimuth {}°, elevation {}°, roll {}°, zoom {}, {projection}; {} frame(s)",
            cam.view.name(),
            cam.azimuth_deg,
            cam.elevation_deg,
            cam.roll_deg,
            cam.zoom,
            self.frames()
        )
    }
}

/// A value given in `given` units in the units of a `volume` (HU → μ = μ_water (1 + HU/1000)).
pub(crate) fn to_volume_units(
    v: f64,
    given: ValueUnits,
    volume: VolumeUnits,
    mu_water: f64,
) -> f64 {
    match (given, volume) {
        (ValueUnits::Hu, VolumeUnits::MuPerMm) => mu_water * (1.0 + v / 1000.0),
        _ => v,
    }
}

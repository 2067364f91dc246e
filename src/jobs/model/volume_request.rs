//! The request of a volume job (`"kind": "volume"`): its input (a stored series, a succeeded job's volume, or
//! a series pulled from a PACS), the `steps` applied to the volume in order, and the `products` made from the
//! result, with their defaults and limits. Model types only: planning and execution live in `imaging`.

use serde::{Deserialize, Deserializer, Serialize};

use crate::mesh::MeshOptions;
use crate::storage::AnyId;
use crate::volume::{Axis, ProjectionKind, Slab};

/// The `kind` of a volume job request.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum VolumeKind {
    Volume,
}

/// `POST /v1/jobs` with `"kind": "volume"`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct VolumeJobRequest {
    pub kind: VolumeKind,
    /// A series id (from `POST /v1/series`), the id of a succeeded job whose volume is the input, or a series
    /// to pull from a PACS.
    pub input: VolumeSource,
    #[serde(default)]
    pub steps: Vec<Step>,
    #[serde(default)]
    pub products: Vec<ProductSpec>,
}

/// Where a volume job's volume comes from.
#[derive(Debug, Clone, PartialEq, Serialize)]
#[serde(untagged)]
pub enum VolumeSource {
    /// A stored series or a succeeded job (its id; which one is found by looking it up).
    Stored(AnyId),
    /// A series pulled from a PACS by C-FIND and C-MOVE when the job runs.
    Pacs(PacsSeries),
}

/// `{"pacs": "<peer>", "series_instance_uid": "…"}`: a series held by a configured DIMSE peer.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PacsSeries {
    /// The AE title of a peer of the `dicom.peers` list.
    pub pacs: String,
    /// The Series Instance UID (0020,000E) on that peer.
    pub series_instance_uid: String,
}

impl From<AnyId> for VolumeSource {
    fn from(id: AnyId) -> Self {
        VolumeSource::Stored(id)
    }
}

impl std::fmt::Display for VolumeSource {
    /// The id of a stored input; `pacs:<peer>/<series uid>` for a pulled one.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            VolumeSource::Stored(id) => write!(f, "{id}"),
            VolumeSource::Pacs(p) => write!(f, "pacs:{}/{}", p.pacs, p.series_instance_uid),
        }
    }
}

impl<'de> Deserialize<'de> for VolumeSource {
    /// A string is an id; an object names a PACS series (unknown fields refused). Errors name what is wrong
    /// instead of serde's "no variant matched".
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        use serde::de::Error as _;
        match serde_json::Value::deserialize(d)? {
            serde_json::Value::String(s) => AnyId::parse(&s)
                .map(VolumeSource::Stored)
                .map_err(D::Error::custom),
            v @ serde_json::Value::Object(_) => serde_json::from_value(v)
                .map(VolumeSource::Pacs)
                .map_err(D::Error::custom),
            _ => Err(D::Error::custom(
                "`input` is a series or job id, or {\"pacs\": <peer>, \"series_instance_uid\": <uid>}",
            )),
        }
    }
}

/// An operation on the whole volume.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(tag = "op", rename_all = "snake_case", deny_unknown_fields)]
pub enum Step {
    /// Trilinear resampling onto cubic voxels of `spacing_mm` (default: the smallest spacing); a tilted series
    /// becomes orthogonal. Interpolation adds no information.
    Resample {
        #[serde(default)]
        spacing_mm: Option<f64>,
    },
    /// Separable Gaussian smoothing, σ in millimetres.
    Gaussian { sigma_mm: f64 },
    /// 3×3×3 median filter.
    Median,
}

fn axial() -> Axis {
    Axis::Axial
}
fn mip() -> ProjectionKind {
    ProjectionKind::Max
}
fn thirty_six() -> usize {
    36
}

/// Something a volume job makes besides the processed volume.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "type", rename_all = "snake_case")]
pub enum ProductSpec {
    /// MIP (`mip`), MinIP (`minip`) or `average` along an array axis, optionally over slices
    /// `slab[0]..slab[1]`.
    Projection(ProjectionSpec),
    /// A reformatted plane, or a series of them.
    Mpr(MprSpec),
    /// A curved plane along a polyline.
    Curved(CurvedSpec),
    /// Projections seen from `frames` angles evenly spread over 360° around the patient's long axis.
    Rotating(RotatingSpec),
    /// An iso-surface (mm, LPS) with its measurements.
    Mesh(MeshOptions),
    /// Volume rendering (ray casting through a transfer function), RGB.
    VolumeRender(super::render_request::VolumeRenderSpec),
    /// Shaded iso-surfaces, opaque or transparent, RGB.
    SurfaceRender(super::render_request::SurfaceRenderSpec),
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ProjectionSpec {
    #[serde(default = "axial")]
    pub axis: Axis,
    #[serde(default = "mip")]
    pub kind: ProjectionKind,
    #[serde(default)]
    pub slab: Option<[usize; 2]>,
}

/// An MPR request. The plane is a principal one (`plane`: axial, coronal, sagittal, through the volume's centre
/// unless `centre_mm` says otherwise) or oblique (`normal`). With `spacing_mm`, a series of planes every
/// `spacing_mm` along the normal covering ±`extent_mm` (default: the whole volume); with `slab`, each plane is a
/// slab `thickness_mm` thick combined by `kind` (e.g. 3 mm MIP every 3 mm).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MprSpec {
    #[serde(default)]
    pub plane: Option<Axis>,
    #[serde(default)]
    pub normal: Option<[f64; 3]>,
    #[serde(default)]
    pub centre_mm: Option<[f64; 3]>,
    /// Image size in pixels (columns, rows); default: the volume's extent in the plane.
    #[serde(default)]
    pub size: Option<[usize; 2]>,
    /// Pixel size (mm); default the smallest voxel spacing.
    #[serde(default)]
    pub pixel_mm: Option<f64>,
    #[serde(default)]
    pub slab: Option<Slab>,
    #[serde(default)]
    pub spacing_mm: Option<f64>,
    #[serde(default)]
    pub extent_mm: Option<f64>,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CurvedSpec {
    /// The polyline (patient mm, LPS), at least two points.
    pub points_mm: Vec<[f64; 3]>,
    /// Direction of image rows (default inferior, −z).
    #[serde(default)]
    pub down: Option<[f64; 3]>,
    /// Rows, centred on the curve.
    pub height: usize,
    /// Pixel size along the curve and across it (mm); default the smallest voxel spacing.
    #[serde(default)]
    pub pixel_mm: Option<f64>,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RotatingSpec {
    #[serde(default = "thirty_six")]
    pub frames: usize,
    #[serde(default = "mip")]
    pub kind: ProjectionKind,
}

/// Largest number of polyline points of a curved MPR.
pub const MAX_CURVE_POINTS: usize = 10_000;
/// Largest number of products or steps in one job.
pub const MAX_ITEMS: usize = 64;
/// Largest σ (mm) of a Gaussian smoothing step.
pub const MAX_SIGMA_MM: f64 = 100.0;
/// Largest number of frames of a rotating projection.
pub const MAX_ROTATING_FRAMES: usize = 720;

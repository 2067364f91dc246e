//! File helpers of the command line: `.npy` arrays and geometry sidecars.

use std::path::{Path, PathBuf};

use ndarray::ArrayD;
use ndarray_npy::{ReadNpyExt, WriteNpyExt};

use crate::recon::geometry::Geometry;

pub type CliResult<T> = Result<T, Box<dyn std::error::Error>>;

/// The geometry sidecar of a data file: `sino.npy` → `sino.json`.
pub fn sidecar(data: &Path) -> PathBuf {
    data.with_extension("json")
}

/// The geometries that ship with ctrecon, by name: the files under `docs/geometries/`, so that
/// `--geometry fan_arc` works from any folder.
pub const BUILT_IN_GEOMETRIES: [(&str, &str); 5] = [
    (
        "parallel",
        include_str!("../../docs/geometries/parallel.json"),
    ),
    (
        "fan_arc",
        include_str!("../../docs/geometries/fan_arc.json"),
    ),
    ("cone", include_str!("../../docs/geometries/cone.json")),
    (
        "parallel3d",
        include_str!("../../docs/geometries/parallel3d.json"),
    ),
    (
        "helical",
        include_str!("../../docs/geometries/helical.json"),
    ),
];

/// A geometry JSON file, or the name of a built-in geometry (`parallel`, `fan_arc`, `cone`, `parallel3d`, `helical`) when no file
/// of that name exists.
pub fn read_geometry(path: &Path) -> CliResult<Geometry> {
    let ext = path.extension().and_then(|e| e.to_str()).unwrap_or("");
    if ext.eq_ignore_ascii_case("xml") || ext.eq_ignore_ascii_case("npy") {
        return Err(format!(
            "{}: an RTK or ASTRA geometry; convert it first: ctrecon geometry --input {} --detector NU NV \
             [--pitch-mm DU DV] --output geometry.json",
            path.display(),
            path.display()
        )
        .into());
    }
    if !path.exists()
        && let Some((_, text)) = BUILT_IN_GEOMETRIES
            .iter()
            .find(|(name, _)| path.as_os_str() == *name)
    {
        return serde_json::from_str(text)
            .map_err(|e| format!("built-in geometry {}: {e}", path.display()).into());
    }
    let text = std::fs::read_to_string(path).map_err(|e| {
        let names: Vec<&str> = BUILT_IN_GEOMETRIES.iter().map(|(n, _)| *n).collect();
        format!(
            "reading {}: {e} (a geometry JSON file, or a built-in geometry: {})",
            path.display(),
            names.join(", ")
        )
    })?;
    serde_json::from_str(&text).map_err(|e| format!("geometry {}: {e}", path.display()).into())
}

pub fn write_geometry(path: &Path, geometry: &Geometry) -> CliResult<()> {
    let text = serde_json::to_string_pretty(geometry)?;
    std::fs::write(path, text + "\n").map_err(|e| format!("writing {}: {e}", path.display()).into())
}

/// Read a float32 or float64 `.npy` as f32.
pub fn read_npy(path: &Path) -> CliResult<ArrayD<f32>> {
    let open = || std::fs::File::open(path).map_err(|e| format!("reading {}: {e}", path.display()));
    match ArrayD::<f32>::read_npy(open()?) {
        Ok(a) => Ok(a),
        Err(_) => {
            let a = ArrayD::<f64>::read_npy(open()?).map_err(|e| {
                format!(
                    "{}: expected a float32 or float64 .npy: {e}",
                    path.display()
                )
            })?;
            Ok(a.mapv(|v| v as f32))
        }
    }
}

pub fn write_npy(path: &Path, array: &ArrayD<f32>) -> CliResult<()> {
    let file =
        std::fs::File::create(path).map_err(|e| format!("writing {}: {e}", path.display()))?;
    array
        .write_npy(std::io::BufWriter::new(file))
        .map_err(|e| format!("writing {}: {e}", path.display()).into())
}

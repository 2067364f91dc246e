//! `ctrecon geometry`: convert a geometry between ctrecon's JSON, its per-view (vector) JSON, RTK's geometry
//! XML and ASTRA's vector arrays, and say whether FBP/FDK can use it.

use std::path::{Path, PathBuf};

use ndarray::Array2;
use ndarray_npy::{ReadNpyExt, WriteNpyExt};

use super::files::{CliResult, read_geometry};
use crate::recon::algorithm::FbpParams;
use crate::recon::geometry::angles::MAX_VIEWS;
use crate::recon::geometry::rtk::{from_rtk_xml, to_rtk_xml};
use crate::recon::geometry::{
    ConeVectors, FanVectors, Geometry, VectorPanel, VectorRow, Views, cone_vectors, fan_vectors,
};

/// Options of `ctrecon geometry`.
#[derive(Debug, clap::Args)]
pub struct GeometryArgs {
    /// The geometry: ctrecon JSON (any type, or a built-in name: parallel, fan_arc, cone), RTK geometry XML
    /// (`.xml`), or ASTRA vectors (`.npy`, `[views, 12]` cone_vec or `[views, 6]` fanflat_vec).
    #[arg(long)]
    pub input: PathBuf,
    /// Where to write it; the format by extension: `.json` (ctrecon's per-view `cone_vectors` /
    /// `fan_vectors`), `.xml` (RTK, for projection images with a centred origin), `.npy` (ASTRA vectors,
    /// float64; ASTRA stores projections `[v][view][u]`, ctrecon `[view][v][u]`).
    #[arg(long)]
    pub output: PathBuf,
    /// Detector columns and rows (cone) or elements (fan): RTK XML and ASTRA `.npy` do not hold them.
    #[arg(long, num_args = 1..=2, value_names = ["NU", "NV"])]
    pub detector: Option<Vec<usize>>,
    /// Detector pitch along u and v in mm (RTK XML input: the projection images' spacing).
    #[arg(long, num_args = 2, value_names = ["DU", "DV"])]
    pub pitch_mm: Option<Vec<f64>>,
}

fn extension(path: &Path) -> String {
    path.extension()
        .and_then(|e| e.to_str())
        .map(str::to_ascii_lowercase)
        .unwrap_or_default()
}

/// Most bytes an ASTRA vector file may have: [`MAX_VIEWS`] rows of 12 float64 and a header.
const MAX_VECTOR_FILE: u64 = (MAX_VIEWS as u64) * 12 * 8 + 65_536;

fn read_vectors_npy(path: &Path) -> CliResult<Array2<f64>> {
    let len = std::fs::metadata(path)
        .map_err(|e| format!("reading {}: {e}", path.display()))?
        .len();
    if len > MAX_VECTOR_FILE {
        return Err(format!(
            "{}: {len} bytes, more than {MAX_VIEWS} views of vectors can take",
            path.display()
        )
        .into());
    }
    let open = || std::fs::File::open(path).map_err(|e| format!("reading {}: {e}", path.display()));
    match Array2::<f64>::read_npy(open()?) {
        Ok(a) => Ok(a),
        Err(_) => Ok(Array2::<f32>::read_npy(open()?)
            .map_err(|e| {
                format!(
                    "{}: expected a 2D float64 or float32 .npy of vectors: {e}",
                    path.display()
                )
            })?
            .mapv(f64::from)),
    }
}

fn input_geometry(args: &GeometryArgs) -> CliResult<Geometry> {
    let detector = args.detector.as_deref();
    let need_panel = |what: &str| -> CliResult<VectorPanel> {
        match detector {
            Some([nu, nv]) => Ok(VectorPanel { nu: *nu, nv: *nv }),
            _ => {
                Err(format!("{what} does not hold the detector size: give --detector NU NV").into())
            }
        }
    };
    match extension(&args.input).as_str() {
        "xml" => {
            let text = crate::scans::read_text(&args.input)?;
            let Some([du, dv]) = args.pitch_mm.as_deref().map(|p| [p[0], p[1]]) else {
                return Err(
                    "an RTK geometry does not hold the detector pitch (the projection images' spacing): give \
                     --pitch-mm DU DV"
                        .into(),
                );
            };
            let panel = need_panel("an RTK geometry")?;
            Ok(Geometry::ConeVectors(
                from_rtk_xml(&text, panel, [du, dv])
                    .map_err(|e| format!("{}: {e}", args.input.display()))?,
            ))
        }
        "npy" => {
            let a = read_vectors_npy(&args.input)?;
            let rows = a.outer_iter();
            match a.ncols() {
                12 => Ok(Geometry::ConeVectors(ConeVectors {
                    detector: need_panel("an ASTRA vector file")?,
                    vectors: rows.map(|r| std::array::from_fn(|i| r[i])).collect(),
                })),
                6 => {
                    let Some([count]) = detector else {
                        return Err(
                            "an ASTRA fan vector file does not hold the detector size: give --detector COUNT"
                                .into(),
                        );
                    };
                    let count = *count;
                    Ok(Geometry::FanVectors(FanVectors {
                        detector: VectorRow { count },
                        vectors: rows.map(|r| std::array::from_fn(|i| r[i])).collect(),
                    }))
                }
                n => Err(format!(
                    "{}: {n} numbers per view; ASTRA vectors have 12 (cone_vec) or 6 (fanflat_vec)",
                    args.input.display()
                )
                .into()),
            }
        }
        _ => read_geometry(&args.input),
    }
}

/// A per-view geometry as JSON with one view per line (a pretty-printed one puts every number on a line).
fn per_view_json(g: &Geometry) -> CliResult<String> {
    let (kind, detector, rows) = match g {
        Geometry::ConeVectors(v) => (
            "cone_vectors",
            serde_json::to_string(&v.detector)?,
            v.vectors.iter().map(|r| r.to_vec()).collect::<Vec<_>>(),
        ),
        Geometry::FanVectors(v) => (
            "fan_vectors",
            serde_json::to_string(&v.detector)?,
            v.vectors.iter().map(|r| r.to_vec()).collect(),
        ),
        _ => return Err("not a per-view geometry".into()),
    };
    let mut lines = Vec::with_capacity(rows.len());
    for row in rows {
        // `+ 0.0` writes −0 as 0.
        let row: Vec<f64> = row.iter().map(|x| x + 0.0).collect();
        lines.push(format!("  {}", serde_json::to_string(&row)?));
    }
    Ok(format!(
        "{{\"type\": \"{kind}\", \"detector\": {detector}, \"vectors\": [\n{}\n]}}\n",
        lines.join(",\n")
    ))
}

pub fn run(args: GeometryArgs) -> CliResult<()> {
    let geometry = input_geometry(&args)?;
    let views = geometry
        .to_views()
        .map_err(|e| format!("{}: {e}", args.input.display()))?;
    if let Views::D3(v) = &views
        && v.detector.shape != crate::recon::geometry::PanelShape::Flat
    {
        return Err(
            "a cylindrical detector has no per-view (cone_vectors), ASTRA cone_vec or RTK XML form; keep the \
             parametric JSON"
                .into(),
        );
    }
    let fbp = crate::recon::analytic::check(&views, &FbpParams::default());
    match extension(&args.output).as_str() {
        "json" => {
            let per_view = match &views {
                Views::D3(v) => Geometry::ConeVectors(cone_vectors(v)),
                Views::Slices(_) => {
                    return Err(
                        "3D parallel beams have no per-view JSON form; keep the parametric JSON".into(),
                    );
                }
                Views::D2(v) => Geometry::FanVectors(fan_vectors(v).ok_or(
                    "parallel beams and arc detectors have no per-view JSON form; keep the parametric JSON",
                )?),
            };
            std::fs::write(&args.output, per_view_json(&per_view)?)
                .map_err(|e| format!("writing {}: {e}", args.output.display()))?;
        }
        "xml" => {
            let Views::D3(v) = &views else {
                return Err("RTK's geometry XML holds cone beams only".into());
            };
            let xml = to_rtk_xml(v)?;
            std::fs::write(&args.output, xml)
                .map_err(|e| format!("writing {}: {e}", args.output.display()))?;
        }
        "npy" => {
            let rows: Vec<Vec<f64>> = match &views {
                Views::D3(v) => cone_vectors(v).vectors.iter().map(|r| r.to_vec()).collect(),
                Views::Slices(_) => {
                    return Err("3D parallel beams have no ASTRA cone_vec form".into());
                }
                Views::D2(v) => fan_vectors(v)
                    .ok_or("parallel beams and arc detectors have no ASTRA fanflat_vec form")?
                    .vectors
                    .iter()
                    .map(|r| r.to_vec())
                    .collect(),
            };
            let width = rows.first().map_or(0, Vec::len);
            let array = Array2::from_shape_vec((rows.len(), width), rows.concat())?;
            let file = std::fs::File::create(&args.output)
                .map_err(|e| format!("writing {}: {e}", args.output.display()))?;
            array
                .write_npy(std::io::BufWriter::new(file))
                .map_err(|e| format!("writing {}: {e}", args.output.display()))?;
        }
        other => {
            return Err(format!(
                "{}: unknown output format {other:?} (.json, .xml or .npy)",
                args.output.display()
            )
            .into());
        }
    }
    let shape = views.data_shape();
    eprintln!(
        "wrote {}: {} views, data shape {shape:?}",
        args.output.display(),
        shape[0]
    );
    match fbp {
        Ok(()) => eprintln!("FBP/FDK: yes (a circular orbit); the iterative methods: yes"),
        Err(e) => eprintln!("FBP/FDK: no ({e}); the iterative methods: yes"),
    }
    Ok(())
}

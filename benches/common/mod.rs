//! Helpers shared by the benches: finding a Python peer to time beside ctrecon, and the cone beam of
//! the peers' cone-beam cases. Not every bench uses every helper.
#![allow(dead_code)]

use std::path::{Path, PathBuf};

/// A Python that imports VTK and NumPy: the project's `.venv-peers` (`scripts/install-peers.sh`) first, then
/// `python3` on the PATH; `None` (with one line saying so, naming `what` was not timed) when neither does.
pub fn vtk_python(what: &str) -> Option<PathBuf> {
    let venv = Path::new(env!("CARGO_MANIFEST_DIR")).join(".venv-peers/bin/python");
    let found = [venv, "python3".into()].into_iter().find(|py| {
        std::process::Command::new(py)
            .args(["-c", "import vtk, numpy"])
            .output()
            .is_ok_and(|o| o.status.success())
    });
    if found.is_none() {
        eprintln!("NOTE: no Python with VTK: {what} not timed");
    }
    found
}

/// The cone beam of `benches/peers/`' cone cases: `views` views over 360°, source 500 mm and panel
/// 750 mm from the source, `det` × `det` pixels of 1.5 mm (1 mm at the centre of rotation).
pub fn peers_cone(views: usize, det: usize) -> ctrecon::recon::geometry::Views3 {
    use ctrecon::recon::geometry::{Angles, ConeBeam, Panel};
    ConeBeam {
        angles: Angles::uniform(views, 360.0),
        dso_mm: 500.0,
        dsd_mm: 750.0,
        detector: Panel {
            nu: det,
            nv: det,
            du_mm: 1.5,
            dv_mm: 1.5,
            offset_u_mm: 0.0,
            offset_v_mm: 0.0,
        },
    }
    .to_views()
    .expect("a valid cone beam")
}

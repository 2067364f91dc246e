//! Helpers shared by the benches that time a Python peer beside ctrecon.

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

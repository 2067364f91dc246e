#!/usr/bin/env bash
# Install the real peers that tests drive or compare against, each in its own idempotent, non-interactive
# section (a section does nothing when its peer is already there): Debian packages, and Python peers in the
# ignored folder .venv-peers/ of the checkout. Run by .ci/run; safe to run again.
set -euo pipefail
cd "$(dirname "$0")/.."
SUDO=""; [ "$(id -u)" -eq 0 ] || SUDO=sudo
export DEBIAN_FRONTEND=noninteractive
APT_UPDATED=""
apt_install() {
  [ -n "$APT_UPDATED" ] || { $SUDO apt-get update -qq; APT_UPDATED=1; }
  $SUDO apt-get install -y -qq --no-install-recommends "$@" >/dev/null
}

# --- Chromium + ChromeDriver (same version) for the web viewer's tests (tests/viewer) -------------------
echo "== peer: chromium"
if ! command -v chromium >/dev/null || ! command -v chromedriver >/dev/null; then
  apt_install chromium chromium-driver
fi

# --- DCMTK (echoscu, storescu, storescp) for the DICOM node's tests (tests/dimse_node.rs) ---------------
echo "== peer: dcmtk"
if ! command -v storescu >/dev/null || ! command -v storescp >/dev/null; then
  apt_install dcmtk
fi

# --- vtk: offscreen rendering (OSMesa) for tests/render_vtk.rs and benches/render_vtk.py ---------------
echo "== peer: vtk"
if ! ldconfig -p 2>/dev/null | grep -q libOSMesa; then
  apt_install libosmesa6 libgl1
fi
if [ ! -x .venv-peers/bin/python ]; then
  python3 -m venv .venv-peers
fi
if ! .venv-peers/bin/python -c "import vtk, numpy" 2>/dev/null \
   || ! cmp -s tests/peers/requirements-vtk.txt .venv-peers/.vtk-requirements; then
  .venv-peers/bin/python -m pip install -q --disable-pip-version-check -r tests/peers/requirements-vtk.txt
  cp tests/peers/requirements-vtk.txt .venv-peers/.vtk-requirements
fi
.venv-peers/bin/python -c "import vtk; print('vtk', vtk.vtkVersion.GetVTKVersion())"

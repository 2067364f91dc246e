#!/usr/bin/env bash
# Install the real peers that tests compare against, each in its own idempotent section, into ignored
# folders of the checkout (.venv-peers/ for Python peers). Run by .ci/run; safe to run again.
set -euo pipefail
cd "$(dirname "$0")/.."

SUDO=""; [ "$(id -u)" -eq 0 ] || SUDO=sudo

# --- vtk: offscreen rendering (OSMesa) for tests/render_vtk.rs and benches/render_vtk.py ---------------
echo "== peer: vtk"
if ! ldconfig -p 2>/dev/null | grep -q libOSMesa; then
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq libosmesa6 libgl1 >/dev/null
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

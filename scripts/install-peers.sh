#!/usr/bin/env bash
# Install the real peers that tests drive or compare against, each in its own idempotent, non-interactive
# section (a section does nothing when its peer is already there): Debian packages, and Python peers in
# ignored folders of the checkout (.venv-peers/ for VTK, .venv-scans/ for tifffile and xrmreader, .venv-rtk/ for
# itk-rtk, .peers/ for schemathesis). Run by .ci/run; safe to run again. A test whose peer is missing prints one skip line, or
# fails when CTRECON_REQUIRE_PEERS=1.
#   scripts/install-peers.sh            every peer
#   scripts/install-peers.sh NAME...    only these (names: chromium, dcmtk, orthanc, postgres, s3,
#                                       netns, vtk, scans, rtk, schemathesis, ts-client)
set -euo pipefail
cd "$(dirname "$0")/.."
root=$(pwd)
peers="$root/.peers"
mkdir -p "$peers"
wanted=("$@")
want() { [ ${#wanted[@]} -eq 0 ] || [[ " ${wanted[*]} " == *" $1 "* ]]; }
SUDO=""; [ "$(id -u)" -eq 0 ] || SUDO=sudo
export DEBIAN_FRONTEND=noninteractive
APT_UPDATED=""
apt_install() {
  [ -n "$APT_UPDATED" ] || { $SUDO apt-get update -qq; APT_UPDATED=1; }
  $SUDO apt-get install -y -qq --no-install-recommends "$@" >/dev/null
}

# --- Chromium + ChromeDriver (same version) for the web viewer's tests (tests/viewer) -------------------
if want chromium; then
  echo "== peer: chromium"
  if ! command -v chromium >/dev/null || ! command -v chromedriver >/dev/null; then
    apt_install chromium chromium-driver
  fi
fi

# --- DCMTK (echoscu, storescu, storescp) for the DICOM node's tests (tests/dimse_node.rs) ---------------
if want dcmtk; then
  echo "== peer: dcmtk"
  if ! command -v storescu >/dev/null || ! command -v storescp >/dev/null; then
    apt_install dcmtk
  fi
fi

# --- Orthanc 1.10 + DICOMweb plugin: the PACS the DICOM node's tests send to and pull from ------------------
if want orthanc; then
  echo "== peer: orthanc"
  if [ ! -x /usr/sbin/Orthanc ] || [ ! -f /usr/share/orthanc/plugins/libOrthancDicomWeb.so ]; then
    apt_install orthanc orthanc-dicomweb
  fi
  # The package starts a system Orthanc on 8042/4242; tests run their own on ports of their own.
  $SUDO service orthanc stop >/dev/null 2>&1 || true
fi

# --- PostgreSQL 15: throwaway clusters (initdb in a temp dir) for the PostgreSQL job store's tests ----------
if want postgres; then
  echo "== peer: postgres"
  if [ ! -x /usr/lib/postgresql/15/bin/initdb ]; then
    apt_install postgresql-15
  fi
  $SUDO service postgresql stop >/dev/null 2>&1 || true
fi

# --- s3s-fs 0.14.1: an S3 server that checks SigV4 signatures, for the object-storage adapter's tests -------
# Built from crates.io into .peers/s3s/ (about 3 minutes on 2 cores; 0.17 needs a newer rustc).
if want s3; then
  echo "== peer: s3"
  if [ ! -x "$peers/s3s/bin/s3s-fs" ]; then
    cargo install --quiet --locked --root "$peers/s3s" s3s-fs --version 0.14.1 --features binary
  fi
  "$peers/s3s/bin/s3s-fs" --version 2>/dev/null || echo "s3s-fs: $peers/s3s/bin/s3s-fs"
fi

# --- iproute2 (`ip netns`, veth, bridge) for the workers in network namespaces (tests/multi_host.rs, root) --
if want netns; then
  echo "== peer: netns"
  if ! command -v ip >/dev/null; then
    apt_install iproute2
  fi
fi

# --- vtk: offscreen rendering (OSMesa) for tests/render_vtk.rs and benches/render_vtk.py ---------------
if want vtk; then
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
fi

# --- scans: Python tifffile, the independent writer of tests/scan_formats.rs's TIFF, Nikon and SkyScan data,
# xrmreader, the independent reader of tests/scan_zeiss.rs's Zeiss .txrm files, and nxtomo (h5py), the writer of
# tests/scan_nxtomo.rs's NeXus NXtomo files ------------------------------------------------------------------
if want scans; then
  echo "== peer: scans"
  if [ ! -x .venv-scans/bin/python ]; then
    python3 -m venv .venv-scans
  fi
  if ! .venv-scans/bin/python -c "import tifffile, numpy, olefile, scipy, skimage, six, tqdm, nxtomo, h5py" 2>/dev/null \
     || ! .venv-scans/bin/python -c "import importlib.metadata as m; m.version('xrmreader')" 2>/dev/null \
     || ! cmp -s tests/peers/requirements-scans.txt .venv-scans/.scans-requirements; then
    .venv-scans/bin/python -m pip install -q --disable-pip-version-check -r tests/peers/requirements-scans.txt
    cp tests/peers/requirements-scans.txt .venv-scans/.scans-requirements
  fi
  .venv-scans/bin/python -c "import tifffile; print('tifffile', tifffile.__version__)"
  .venv-scans/bin/python -c "import importlib.metadata as m; print('xrmreader', m.version('xrmreader'))"
  .venv-scans/bin/python -c "import nxtomo, h5py; print('nxtomo', nxtomo.__version__, 'h5py', h5py.__version__)"
fi

# --- rtk: itk-rtk, the independent reader and writer of RTK geometry XML in tests/geometry_rtk.rs ------------
if want rtk; then
  echo "== peer: rtk"
  if [ ! -x .venv-rtk/bin/python ]; then
    python3 -m venv .venv-rtk
  fi
  if ! .venv-rtk/bin/python -c "from itk import RTK" 2>/dev/null \
     || ! cmp -s tests/peers/requirements-rtk.txt .venv-rtk/.rtk-requirements; then
    .venv-rtk/bin/python -m pip install -q --disable-pip-version-check -r tests/peers/requirements-rtk.txt
    cp tests/peers/requirements-rtk.txt .venv-rtk/.rtk-requirements
  fi
  .venv-rtk/bin/python -c "import itk; from itk import RTK; print('itk', itk.Version.GetITKVersion())"
fi

# --- schemathesis: property-based tests of openapi.yaml against the running server ------------------------
# tests/contract_schemathesis.rs runs .peers/venv/bin/schemathesis. Pinned with every dependency in
# tests/peers/schemathesis-requirements.txt (regenerate: fresh venv, pip install schemathesis==X, pip freeze).
if want schemathesis; then
    echo "== peer: schemathesis"
    req="$root/tests/peers/schemathesis-requirements.txt"
    venv="$peers/venv"
    stamp="$venv/.schemathesis-requirements"
    # Python 3.12 or later where there is one: 3.11 up to 3.11.7 fails with "AST constructor recursion depth
    # mismatch" while generating the deepest request schemas (POST /v1/jobs).
    py=python3
    for c in python3.13 python3.12 $(ls -d "$(pyenv root 2>/dev/null || echo /nonexistent)"/versions/3.1[2-9]*/bin/python3 2>/dev/null); do
        if "$c" -c 'import sys; sys.exit(sys.version_info < (3, 12))' 2>/dev/null; then py=$c; break; fi
    done
    want_stamp=$(cat "$req"; "$py" --version)
    if [ -x "$venv/bin/schemathesis" ] && [ "$want_stamp" = "$(cat "$stamp" 2>/dev/null)" ]; then
        echo "schemathesis: already installed ($("$venv/bin/schemathesis" --version))"
    else
        rm -rf "$venv"
        if ! "$py" -m venv "$venv" 2>/dev/null; then
            # Debian ships venv separately.
            SUDO=""; [ "$(id -u)" -eq 0 ] || SUDO=sudo
            $SUDO apt-get update -qq && DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq python3-venv
            rm -rf "$venv"
            "$py" -m venv "$venv"
        fi
        "$venv/bin/pip" install --quiet --disable-pip-version-check --no-input -r "$req"
        printf '%s' "$want_stamp" > "$stamp"
        echo "schemathesis: installed ($("$venv/bin/schemathesis" --version))"
    fi
fi

# --- A client generated from openapi.yaml (tests/generated_client.rs): openapi-typescript, openapi-fetch and
# typescript from the npm registry, pinned by tests/peers/ts-client/package-lock.json, into its node_modules/.
if want ts-client; then
    echo "== peer: ts-client"
    dir="$root/tests/peers/ts-client"
    if ! command -v npm >/dev/null; then
        apt_install nodejs npm
    fi
    if [ -f "$dir/node_modules/.package-lock.json" ] && cmp -s "$dir/package-lock.json" "$dir/node_modules/.ctrecon-lock"; then
        echo "ts-client: already installed"
    else
        (cd "$dir" && npm ci --no-audit --no-fund --loglevel=error)
        cp "$dir/package-lock.json" "$dir/node_modules/.ctrecon-lock"
        echo "ts-client: installed (node $(node --version))"
    fi
fi

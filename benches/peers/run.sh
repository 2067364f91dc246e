#!/usr/bin/env bash
# Install the pinned peers into benches/peers/.venv (once), build the ctrecon binary, and run the
# peer benchmark: `benches/peers/run.sh [--quick] [--only TEXT] [--threads N]`, or CGLS iteration by
# iteration beside ASTRA: `benches/peers/run.sh --cgls-paths [--quick] [--iterations N] [--at K]`. Not run by CI.
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
root="$(cd "$here/../.." && pwd)"
venv="$here/.venv"
if [ ! -x "$venv/bin/python" ] || ! cmp -s "$here/requirements.txt" "$venv/requirements.txt"; then
    python3 -m venv "$venv"
    "$venv/bin/pip" install --quiet --upgrade pip
    "$venv/bin/pip" install --quiet -r "$here/requirements.txt"
    cp "$here/requirements.txt" "$venv/requirements.txt"
fi
(cd "$root" && cargo build --release --quiet --bin ctrecon)
script=peers.py
if [ "${1:-}" = "--cgls-paths" ]; then
    script=cgls_paths.py
    shift
fi
exec "$venv/bin/python" "$here/$script" "$@"

#!/usr/bin/env bash
# Install the real peers that ctrecon's tests run against, into .peers/ (ignored by git). Idempotent and
# non-interactive: a peer already installed at its pinned version is left alone. One section per peer; a
# test whose peer is missing prints one skip line, or fails when CTRECON_REQUIRE_PEERS=1 (as .ci/run sets).
#   scripts/install-peers.sh            every peer
#   scripts/install-peers.sh NAME...    only these (names: schemathesis)
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
peers="$root/.peers"
mkdir -p "$peers"
wanted=("$@")
want() { [ ${#wanted[@]} -eq 0 ] || [[ " ${wanted[*]} " == *" $1 "* ]]; }

# --- schemathesis: property-based tests of openapi.yaml against the running server ------------------------
# tests/contract_schemathesis.rs runs .peers/venv/bin/schemathesis. Pinned with every dependency in
# tests/peers/schemathesis-requirements.txt (regenerate: fresh venv, pip install schemathesis==X, pip freeze).
if want schemathesis; then
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

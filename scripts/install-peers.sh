#!/usr/bin/env bash
# Installs the real peers the tests drive (Debian packages), idempotent and non-interactive. One section per
# peer; a section does nothing when its peer is already there.
set -euo pipefail
SUDO=""; [ "$(id -u)" -eq 0 ] || SUDO=sudo
export DEBIAN_FRONTEND=noninteractive

# Headless Chromium + ChromeDriver (same version) for the web viewer's tests (tests/viewer.rs).
if ! command -v chromium >/dev/null || ! command -v chromedriver >/dev/null; then
  $SUDO apt-get update -qq
  $SUDO apt-get install -y -qq --no-install-recommends chromium chromium-driver
fi

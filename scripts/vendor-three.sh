#!/usr/bin/env bash
# Refresh the vendored three.js of the web viewer from the npm registry: web/vendor/three/ gets
# build/three.module.js, build/three.core.js, OrbitControls.js (its `from 'three'` import made relative) and
# the licence. Needs npm and network access; ctrecon itself builds without either.
set -euo pipefail
VERSION="${1:?usage: scripts/vendor-three.sh VERSION (e.g. 0.187.0)}"
cd "$(dirname "$0")/.."
T=$(mktemp -d); trap 'rm -rf "$T"' EXIT
(cd "$T" && npm pack --silent "three@$VERSION" >/dev/null && tar xzf "three-$VERSION.tgz")
D=web/vendor/three
cp "$T/package/build/three.module.js" "$T/package/build/three.core.js" "$T/package/LICENSE" "$D/"
sed "s#^} from 'three';#} from './three.module.js';#" "$T/package/examples/jsm/controls/OrbitControls.js" > "$D/OrbitControls.js"
SHA=$(sha256sum "$T/three-$VERSION.tgz" | cut -c1-64)
sed -i -E "s/three@[0-9.]+/three@$VERSION/g; s/Version: [0-9.]+/Version: $VERSION/; s/sha256 \`[0-9a-f]+\`/sha256 \`$SHA\`/" "$D/README.md"
echo "three.js $VERSION vendored into $D (tarball sha256 $SHA)"

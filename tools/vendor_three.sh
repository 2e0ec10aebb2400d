#!/usr/bin/env bash
# Vendor three.js into the Python package (the /viewer page must work offline: no CDN).
#
#   tools/vendor_three.sh [VERSION]        (default: the version recorded in VERSION below)
#
# What it does: `npm pack three@VERSION` (the npm registry's tarball), then minifies with esbuild
# (npm's esbuild package, installed into a temporary folder) the files the viewer imports: the
# module build (build/three.module.js + build/three.core.js, which it imports) and the addons
# GLTFLoader (+ utils/BufferGeometryUtils.js, utils/SkeletonUtils.js, which it imports) and
# OrbitControls. Minifying keeps the module names and import paths, so the files work exactly as
# the unminified ones (three's npm package stopped shipping *.min.js builds). Copies three's
# LICENSE, and records the version and the tools in runtime/stream/static/three/VERSION.
# Needs node + npm and network access to the npm registry; run from the repository root.
set -euo pipefail
cd "$(dirname "$0")/.."
DEST=runtime/stream/static/three
VERSION="${1:-$(sed -n 's/^three //p' "$DEST/VERSION" 2>/dev/null || true)}"
VERSION="${VERSION:-$(npm view three version)}"
TMP="$(mktemp -d)"
trap 'rm -rf "$TMP"' EXIT
( cd "$TMP" && npm pack --silent "three@$VERSION" >/dev/null && tar xzf "three-$VERSION.tgz" )
npm install --silent --no-save --no-audit --no-fund --prefix "$TMP/tools" esbuild >/dev/null
ESBUILD="$TMP/tools/node_modules/.bin/esbuild"
rm -rf "$DEST"
mkdir -p "$DEST/addons/loaders" "$DEST/addons/utils" "$DEST/addons/controls"
min() {  # min SRC DEST: minify one ES module, keeping its imports and exports
  "$ESBUILD" "$TMP/package/$1" --minify --format=esm --target=es2020 --log-level=warning --outfile="$DEST/$2"
}
min build/three.core.js three.core.js
min build/three.module.js three.module.js
min examples/jsm/loaders/GLTFLoader.js addons/loaders/GLTFLoader.js
min examples/jsm/utils/BufferGeometryUtils.js addons/utils/BufferGeometryUtils.js
min examples/jsm/utils/SkeletonUtils.js addons/utils/SkeletonUtils.js
min examples/jsm/controls/OrbitControls.js addons/controls/OrbitControls.js
cp "$TMP/package/LICENSE" "$DEST/LICENSE"
{
  echo "three $VERSION"
  echo "source: npm pack three@$VERSION (https://www.npmjs.com/package/three), MIT licence (LICENSE)"
  echo "minified with esbuild $("$ESBUILD" --version) (--minify --format=esm --target=es2020) by tools/vendor_three.sh"
} > "$DEST/VERSION"
du -b "$DEST"/*.js "$DEST"/addons/*/*.js | sort -n
echo "total: $(du -cb "$DEST"/*.js "$DEST"/addons/*/*.js | tail -1 | cut -f1) bytes"

#!/usr/bin/env bash
# Builds ../assets/viewer3d.js, physmorph's offline 3D viewer (src/main.js with three.js and Spark),
# from the exact versions pinned in package-lock.json: a classic (non-module) IIFE script that a page
# opened as file:// loads with <script src="viewer3d.js">. Needs Node >= 18 and npm (run once, offline
# afterwards only if node_modules/ is kept). The libraries' licenses are in ../assets/LICENSES.md.
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
cd "$here"
npm ci --no-audit --no-fund
./node_modules/.bin/esbuild src/main.js \
  --bundle --format=iife --minify --target=es2020 --legal-comments=eof \
  --outfile=../assets/viewer3d.js
ls -l ../assets/viewer3d.js

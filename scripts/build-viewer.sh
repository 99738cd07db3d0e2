#!/usr/bin/env bash
# Rebuilds the viewer bundle relfusiond embeds (server/assets/viewer/) from server/viewer/:
# installs the locked npm packages (three, protobufjs, esbuild), bundles and minifies the
# page's code with them, and gathers the bundled libraries' licences.
# Usage: bash scripts/build-viewer.sh   (then rebuild relfusiond; commit the assets)
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
cd "$root/server/viewer"
npm ci --no-audit --no-fund >&2
npm run --silent build >&2
{
  echo "Libraries bundled into viewer.js, with their licences."
  for pkg in three protobufjs long; do
    version=$(node -p "require('./node_modules/$pkg/package.json').version")
    printf '\n==== %s %s ====\n\n' "$pkg" "$version"
    cat "node_modules/$pkg/LICENSE"
  done
  printf '\n==== notices kept by the bundler ====\n\n'
  cat ../assets/viewer/viewer.js.LEGAL.txt
} > ../assets/viewer/licenses.txt
rm ../assets/viewer/viewer.js.LEGAL.txt
ls -l ../assets/viewer/ >&2
echo "viewer.js: $(wc -c < ../assets/viewer/viewer.js) bytes, $(gzip -9c ../assets/viewer/viewer.js | wc -c) gzipped" >&2

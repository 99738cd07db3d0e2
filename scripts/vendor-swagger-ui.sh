#!/usr/bin/env bash
# Refreshes the Swagger UI files relfusiond embeds (server/assets/swagger-ui/) from the npm
# package swagger-ui-dist. Usage: bash scripts/vendor-swagger-ui.sh [VERSION]
set -euo pipefail
version=${1:-5.35.0}
root=$(cd "$(dirname "$0")/.." && pwd)
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
(cd "$work" && npm pack "swagger-ui-dist@$version" >/dev/null && tar xzf swagger-ui-dist-*.tgz)
dest="$root/server/assets/swagger-ui"
for f in swagger-ui-bundle.js swagger-ui.css LICENSE NOTICE swagger-ui-bundle.js.LICENSE.txt; do
  cp "$work/package/$f" "$dest/$f"
done
sed -i "s/swagger-ui-dist\` [0-9.]*/swagger-ui-dist\` $version/" "$dest/README.md"
echo "swagger-ui-dist $version vendored into $dest"

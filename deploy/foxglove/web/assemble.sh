#!/usr/bin/env bash
# Assemble the live view's browser app into OUTDIR from npm-registry packages only (no build step):
# the prebuilt bundle of Foxglove Studio 1.48 (@foxglove/studio-base, MPL-2.0, the last open-source
# release), React 17 (its UMD externals), this folder's host page and the project's layout.
#
#   deploy/foxglove/web/assemble.sh OUTDIR        (make view-web runs it into .run/foxglove-web)
#
# Studio 1.48's WebSocket client asks for the protocol by its first name `foxglove.websocket.v1`, which
# the viewer serves (services/viewer/view_server.py) beside foxglove-sdk's `foxglove.sdk.v1`.
set -euo pipefail
HERE="$(cd "$(dirname "$0")" && pwd)"
OUT="${1:?usage: assemble.sh OUTDIR}"
STUDIO=1.48.0
REACT=17.0.2
command -v npm >/dev/null || { echo "assemble.sh: needs npm (apt-get install npm)" >&2; exit 2; }
if [ ! -f "$OUT/.studio-$STUDIO" ]; then
  TMP="$(mktemp -d)"
  trap 'rm -rf "$TMP"' EXIT
  (cd "$TMP" && npm pack --silent "@foxglove/studio-base@$STUDIO" "react@$REACT" "react-dom@$REACT" >/dev/null)
  tar xzf "$TMP/foxglove-studio-base-$STUDIO.tgz" -C "$TMP" package/assets
  mkdir -p "$OUT"
  rm -rf "$OUT/assets"
  mv "$TMP/package/assets" "$OUT/assets"
  tar xzf "$TMP/react-$REACT.tgz" -O package/umd/react.production.min.js >"$OUT/react.production.min.js"
  tar xzf "$TMP/react-dom-$REACT.tgz" -O package/umd/react-dom.production.min.js >"$OUT/react-dom.production.min.js"
  rm -f "$OUT"/.studio-*
  touch "$OUT/.studio-$STUDIO"
fi
cp "$HERE/index.html" "$HERE/boot.js" "$HERE/../rmmdet-layout.json" "$OUT/"
echo "$OUT/index.html"

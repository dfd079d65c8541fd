#!/usr/bin/env bash
# Assemble the live view's browser app into OUTDIR from npm-registry packages only (no build step):
# the prebuilt bundle of Foxglove Studio 1.48 (@foxglove/studio-base, MPL-2.0, the last open-source
# release), React 17 (its UMD externals), this folder's host page and the project's layout.
#
#   deploy/foxglove/web/assemble.sh OUTDIR        (make view-web runs it into .run/foxglove-web)
#
# One patch: Studio 1.48's WebSocket client offers only the subprotocol name
# `foxglove.websocket.v1`, while foxglove-sdk servers (the viewer) accept only its successor's name
# `foxglove.sdk.v1`, the same protocol renamed; the client is made to offer and accept both.
set -euo pipefail
HERE="$(cd "$(dirname "$0")" && pwd)"
OUT="${1:?usage: assemble.sh OUTDIR}"
STUDIO=1.48.0
REACT=17.0.2
PATCH=1  # bump when the patch below changes: an assembled copy is redone
command -v npm >/dev/null || { echo "assemble.sh: needs npm (apt-get install npm)" >&2; exit 2; }
if [ ! -f "$OUT/.studio-$STUDIO-patch$PATCH" ]; then
  TMP="$(mktemp -d)"
  trap 'rm -rf "$TMP"' EXIT
  (cd "$TMP" && npm pack --silent "@foxglove/studio-base@$STUDIO" "react@$REACT" "react-dom@$REACT" >/dev/null)
  tar xzf "$TMP/foxglove-studio-base-$STUDIO.tgz" -C "$TMP" package/assets
  mkdir -p "$OUT"
  rm -rf "$OUT/assets"
  mv "$TMP/package/assets" "$OUT/assets"
  tar xzf "$TMP/react-$REACT.tgz" -O package/umd/react.production.min.js >"$OUT/react.production.min.js"
  tar xzf "$TMP/react-dom-$REACT.tgz" -O package/umd/react-dom.production.min.js >"$OUT/react-dom.production.min.js"
  sed -i \
    -e 's/new WorkerSocketAdapter(this._url, \[FoxgloveClient.SUPPORTED_SUBPROTOCOL\])/new WorkerSocketAdapter(this._url, ["foxglove.sdk.v1", FoxgloveClient.SUPPORTED_SUBPROTOCOL])/' \
    -e 's/new WebSocket(this._url, \[FoxgloveClient.SUPPORTED_SUBPROTOCOL\])/new WebSocket(this._url, ["foxglove.sdk.v1", FoxgloveClient.SUPPORTED_SUBPROTOCOL])/' \
    -e 's/if (this.ws.protocol !== FoxgloveClient.SUPPORTED_SUBPROTOCOL) {/if (this.ws.protocol !== FoxgloveClient.SUPPORTED_SUBPROTOCOL \&\& this.ws.protocol !== "foxglove.sdk.v1") {/' \
    "$OUT/assets/index.js"
  if [ "$(grep -o 'foxglove\.sdk\.v1' "$OUT/assets/index.js" | wc -l)" -ne 3 ]; then
    echo "assemble.sh: the subprotocol patch did not apply to studio-base $STUDIO" >&2
    exit 1
  fi
  rm -f "$OUT"/.studio-*
  touch "$OUT/.studio-$STUDIO-patch$PATCH"
fi
cp "$HERE/index.html" "$HERE/boot.js" "$HERE/../rmmdet-layout.json" "$OUT/"
echo "$OUT/index.html"

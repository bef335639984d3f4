#!/usr/bin/env bash
# Regenerates the report page screenshots in docs/report/: the demo's page and the page of a
# DiLiGenT-layout set (../shared/data/diligent-bear, the real DiLiGenT bear, when present).
# Usage: docs/report/screenshots.sh [psscan binary]   (make report-screenshots)
set -euo pipefail
cd "$(dirname "$0")/../.."
PSSCAN=${1:-target/release/psscan}
WORK=target/report-screenshots
DILIGENT=${DILIGENT:-../shared/data/diligent-bear}
BROWSER=$(command -v chromium || command -v chromium-browser || command -v google-chrome || true)
if [ -z "$BROWSER" ]; then
  echo "report-screenshots: no chromium on PATH (./.ci/install-deps installs it)" >&2
  exit 1
fi
mkdir -p "$WORK"

shoot() { # page.html out.png height
  "$BROWSER" --headless --no-sandbox --use-angle=swiftshader --enable-unsafe-swiftshader \
    --hide-scrollbars --force-device-scale-factor=0.75 --user-data-dir="$WORK/profile" --virtual-time-budget=20000 \
    --window-size=1400,"$3" --screenshot="$2" "file://$(realpath "$1")" 2>/dev/null
  echo "wrote $2"
}

"$PSSCAN" demo --out "$WORK/demo" --width 1024 --height 768 --sheen -q
# The page with derived height and roughness, as `psscan derive` then `psscan report --derived`
# give it.
"$PSSCAN" derive "$WORK/demo/maps" --out "$WORK/demo-derived" --height --roughness vmf --force -q
"$PSSCAN" report "$WORK/demo/maps" --derived "$WORK/demo-derived" >/dev/null
shoot "$WORK/demo/maps/report.html" docs/report/demo.png 5200

if [ -d "$DILIGENT" ]; then
  "$PSSCAN" solve "$DILIGENT" --out "$WORK/diligent" --force -q
  shoot "$WORK/diligent/report.html" docs/report/diligent-bear.png 5200
else
  echo "report-screenshots: $DILIGENT not found: DiLiGenT screenshot not regenerated" >&2
fi

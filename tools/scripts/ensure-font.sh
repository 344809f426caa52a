#!/usr/bin/env bash
# Plot labels (gprflow eval --plot, gprflow radargram) need a font: Debian's DejaVu Sans.
set -euo pipefail
if [[ ! -f /usr/share/fonts/truetype/dejavu/DejaVuSans.ttf ]] && command -v apt-get >/dev/null && [[ $(id -u) == 0 ]]; then
    apt-get install -y --no-install-recommends fonts-dejavu-core >/dev/null 2>&1 ||
        { apt-get update >/dev/null && apt-get install -y --no-install-recommends fonts-dejavu-core >/dev/null; }
fi

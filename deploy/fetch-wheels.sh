#!/usr/bin/env bash
# Download every pinned wheel the image needs into a local wheelhouse, so that `docker build`
# installs them with --no-index: no package index is needed at build time.
#
# Use it when the Docker build cannot reach a package index itself: an offline robot or lab, a
# build network without DNS, or a TLS-intercepting proxy whose CA the host trusts but the
# container does not. The Dockerfile uses the wheelhouse automatically when it finds wheels in
# build/wheelhouse/ (git-ignored, part of the Docker build context); with none it uses the index.
#
# Usage: deploy/fetch-wheels.sh [--dest DIR] [--python-version 3.11] [--platform TAG ...]
#   --dest DIR            default: build/wheelhouse in the repository (what the Dockerfile reads)
#   --python-version X.Y  the image's Python (default: 3.11, the bookworm base)
#   --platform TAG        wheel platform tag, repeatable. Default: manylinux tags of this machine's
#                         architecture. For an arm64 robot image, e.g.:
#                         --platform manylinux2014_aarch64 --platform manylinux_2_28_aarch64
#
# Example (offline build with the locally built base image):
#   deploy/build-base-image.sh
#   deploy/fetch-wheels.sh
#   docker build --build-arg BASE_IMAGE=ballbot-vision/python-base:3.11-bookworm -t ballbot-vision .
set -euo pipefail

HERE=$(cd "$(dirname "$0")" && pwd)
ROOT=$(dirname "$HERE")
DEST="$ROOT/build/wheelhouse"
PYV=3.11
PLATFORMS=()
while [ $# -gt 0 ]; do
    case "$1" in
        --dest) DEST=${2:?}; shift 2 ;;
        --python-version) PYV=${2:?}; shift 2 ;;
        --platform) PLATFORMS+=("${2:?}"); shift 2 ;;
        -h|--help) sed -n '2,/^set -euo/p' "$0" | sed -e '$d' -e 's/^# \{0,1\}//'; exit 0 ;;
        *) echo "unknown option: $1" >&2; exit 2 ;;
    esac
done
if [ ${#PLATFORMS[@]} -eq 0 ]; then
    arch=$(uname -m)
    # glibc of Debian bookworm is 2.36: every manylinux tag up to 2_36 runs on it.
    for t in manylinux2014 manylinux_2_17 manylinux_2_24 manylinux_2_27 manylinux_2_28 \
             manylinux_2_31 manylinux_2_34 manylinux_2_35 manylinux_2_36 linux; do
        PLATFORMS+=("${t}_${arch}")
    done
fi
PLATFORM_ARGS=()
for p in "${PLATFORMS[@]}"; do PLATFORM_ARGS+=(--platform "$p"); done

mkdir -p "$DEST"
PY=${PYTHON:-python3}
ABI="cp${PYV/./}"
# Runtime: exactly the pins, binary wheels for the image's Python and platform.
"$PY" -m pip download --disable-pip-version-check --no-deps --only-binary=:all: \
    --python-version "$PYV" --implementation cp --abi "$ABI" --abi abi3 --abi none \
    "${PLATFORM_ARGS[@]}" \
    -r <(grep -v '^#' "$HERE/constraints.txt") -d "$DEST"
# Build backend: pure-Python wheels.
"$PY" -m pip download --disable-pip-version-check --no-deps --only-binary=:all: \
    -r <(grep -v '^#' "$HERE/build-constraints.txt") -d "$DEST"
# Wheels of versions no longer pinned only grow the Docker build context: remove them.
"$PY" - "$HERE/constraints.txt" "$HERE/build-constraints.txt" "$DEST" <<'EOF'
import re, sys
from pathlib import Path
norm = lambda s: re.sub(r"[-_.]+", "_", s).lower()
pins = set()
for f in sys.argv[1:3]:
    for line in Path(f).read_text().splitlines():
        line = line.split("#")[0].strip()
        if "==" in line:
            name, version = (x.strip() for x in line.split(";")[0].split("=="))
            pins.add((norm(name), version))
for w in Path(sys.argv[3]).glob("*.whl"):
    name, version = w.name.split("-")[:2]
    if (norm(name), version) not in pins:
        print(f"removing {w.name} (not pinned any more)", file=sys.stderr)
        w.unlink()
EOF
echo "wheelhouse: $DEST ($(ls "$DEST"/*.whl | wc -l) wheels, $(du -sh "$DEST" | cut -f1))" >&2

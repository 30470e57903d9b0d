#!/bin/sh
# Wall time of a fresh `pip install .`: a clean virtual environment, an empty cargo target
# directory and a clean copy of the repository (crates already downloaded to ~/.cargo are
# reused, as on any machine that has built a Rust crate before). Prints the seconds.
# Usage: sh benches/install_time.sh [python]
set -eu
PY=${1:-python3}
ROOT=$(cd "$(dirname "$0")/.." && pwd)
WORK=$(mktemp -d)
trap 'rm -rf "$WORK"' EXIT
git -C "$ROOT" archive --format=tar HEAD | tar -x -C "$WORK" --one-top-level=src
"$PY" -m venv "$WORK/venv"
"$WORK/venv/bin/pip" install -q --upgrade pip >/dev/null
START=$(date +%s.%N)
CARGO_TARGET_DIR="$WORK/target" "$WORK/venv/bin/pip" install -q "$WORK/src"
END=$(date +%s.%N)
"$WORK/venv/bin/accelcal" --version >/dev/null
echo "fresh pip install . : $(echo "$END - $START" | bc) s (nproc $(nproc), load $(cut -d' ' -f1-3 /proc/loadavg))"

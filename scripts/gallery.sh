#!/usr/bin/env bash
# Regenerate the README's gallery (docs/gallery/*.png) with the project's own
# `--render`, on the CPU backend (no GPU needed):
#   scripts/gallery.sh
# Each picture is a job's input and result side by side, coloured by the
# realised scale factor, 800x400 pixels.
set -euo pipefail
cd "$(dirname "$0")/.."
cargo build --release --all-features --quiet
bin=target/release/metricdeform
out=docs/gallery
mkdir -p "$out"
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
size=800x400

"$bin" demo --backend cpu --quiet --out "$tmp/spot.obj" \
  --render "$out/demo.png" --render-size "$size"
"$bin" deform examples/bunny-ears.toml --backend cpu --quiet --out "$tmp/bunny.obj" \
  --render "$out/bunny-ears.png" --render-size "$size"
"$bin" deform examples/homer-table1.toml --backend cpu --quiet --out "$tmp/homer.obj" \
  --render "$out/homer-table1.png" --render-size "$size" --view front
"$bin" measure examples/bunny-ears.toml \
  --render "$out/bunny-ears-selection.png" --render-size 600x400 2>/dev/null
ls -l "$out"

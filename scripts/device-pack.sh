#!/usr/bin/env bash
# Builds the release binaries a device call needs and packs them into
# .devbin/ (git-ignored; name it in the device tool's `carry`, with .gl, the
# Vulkan loader's .deb files: ../.library/device/README.md says how to fetch
# them). The device has no Rust; a stripped, xz-packed set is about 15 MB,
# under the 64 MiB a call may carry. Then, on the device, from the
# repository root: `bash scripts/device-check.sh` (its header says what it runs).
set -euo pipefail
cd "$(dirname "$0")/.."
cargo build --release
# The bench's or test's own executable (not the crate's binary, which cargo
# lists too, and in an order that changes with what it rebuilt).
exe() { cargo "$@" --message-format=json 2>/dev/null | grep -v '"kind":\["bin"\]' \
  | sed -n 's/.*"executable":"\([^"]*\)".*/\1/p' | tail -1; }
pipeline=$(exe bench --bench pipeline --no-run)
cholesky=$(exe bench --features bench-kernels --bench cholesky_teams --no-run)
factor=$(exe bench --bench cholesky_factor --no-run)
ordering=$(exe bench --bench fill_ordering --no-run)
hoststeps=$(exe bench --bench host_steps --no-run)
conformance=$(exe test --release --all-features --no-run --test conformance)
kernels=$(exe test --release --all-features -p solver-gpu --no-run --test kernels)
tmp=$(mktemp -d)
cp target/release/metricdeform "$tmp/metricdeform"
cp "$pipeline" "$tmp/pipeline-bench"
cp "$cholesky" "$tmp/cholesky-bench"
cp "$factor" "$tmp/factor-bench"
cp "$ordering" "$tmp/ordering-bench"
cp "$hoststeps" "$tmp/host-steps"
cp "$conformance" "$tmp/conformance"
cp "$kernels" "$tmp/kernels"
strip "$tmp"/*
{ git rev-parse --short HEAD | tr -d '\n'; git diff --quiet HEAD || printf '+uncommitted'; echo; } > "$tmp/COMMIT"
mkdir -p .devbin
tar cJf .devbin/bin.tar.xz -C "$tmp" .
rm -rf "$tmp"
ls -l .devbin/bin.tar.xz

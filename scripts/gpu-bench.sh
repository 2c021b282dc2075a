#!/usr/bin/env bash
# One-command GPU benchmark: the pipeline rows at about 100k, 1.2M and 4.3M faces
# (homer, every edge cut in 3, 10 and 19; two girths and the volume) on the CPU
# and GPU backends of the same machine, printed as one Markdown table with the
# device and the CPU named. For BENCHMARKS.md ("Real GPU").
#
#   scripts/gpu-bench.sh [ROW ...]        rows: 100k 1m 4m (default: all three)
#
# Binaries: $BIN (default target/release) must hold `metricdeform` and the
# pipeline bench as `pipeline-bench`; build them with
#   cargo build --release && cargo bench --bench pipeline --no-run
#   cp "$(ls -t target/release/deps/pipeline-* | grep -v '\.d$' | head -1)" target/release/pipeline-bench
#   git rev-parse --short HEAD > target/release/COMMIT
# and, optionally, the Cholesky solves' bench (one lane per dot product
# against teams, per application; rows 100k and 1m) as `cholesky-bench`:
#   cargo bench --features bench-kernels --bench cholesky_teams --no-run
#   cp "$(ls -t target/release/deps/cholesky_teams-* | grep -v '\.d$' | head -1)" target/release/cholesky-bench
# ($BIN/COMMIT names the binaries' commit in the header line: binaries carried
# to another machine are not that machine's checkout.)
# The bench reads its meshes from data/meshes under the repository root it was
# built in (its CARGO_MANIFEST_DIR); run this script from the repository root,
# or link that path to it on another machine. The CPU rows run in their own
# processes, so each row's peak memory is its backend's alone. The GPU row also
# runs the CPU backend after it and prints how far apart the two results are
# (parity: within 1e-3 % of the bbox diagonal) and the cost proxies.
set -euo pipefail
cd "$(dirname "$0")/.."
BIN=${BIN:-target/release}
rows=("$@")
[ ${#rows[@]} -gt 0 ] || rows=(100k 1m 4m)
for b in metricdeform pipeline-bench; do
  [ -x "$BIN/$b" ] || { echo "gpu-bench: $BIN/$b is missing (see the header of $0)" >&2; exit 2; }
done

device=$("$BIN/metricdeform" adapters 2>/dev/null | sed -n 's/^`--backend gpu` would use: \(.*\) (set .*/\1/p')
cpu=$( (lscpu 2>/dev/null | sed -n 's/^Model name: *//p' | head -1) || true)
if [ -s "$BIN/COMMIT" ]; then
  commit="binaries of $(head -c 40 "$BIN/COMMIT")"
else
  commit="checkout $(git rev-parse --short HEAD 2>/dev/null || echo '?') (no $BIN/COMMIT: the binaries' own commit is unknown)"
fi
echo "device: ${device:-none}; CPU: ${cpu:-unknown}, $(nproc) cores; $(date -u +%Y-%m-%d); $commit"
log=${LOG:-$(mktemp -d)}
mkdir -p "$log"
# Field k of a row's table line: | name | faces | multipliers | iterations | load | sd | ft | total | err | peak |
field() { awk -F'|' -v k="$2" '/^\| girths/ {gsub(/ /, "", $k); print $k; exit}' "$1"; }
echo
echo "| row | faces | cpu s | gpu s | gpu vs cpu | cpu peak MiB | gpu peak MiB | max metric error % (gpu) | gpu - cpu, % of bbox diagonal |"
echo "|---|---|---|---|---|---|---|---|---|"
for r in "${rows[@]}"; do
  name="girths-homer-$r"
  "$BIN/pipeline-bench" --row "$name" per_constraint --backend cpu >"$log/$r.cpu" 2>"$log/$r.cpu.err" || true
  "$BIN/pipeline-bench" --row "$name" per_constraint --backend gpu >"$log/$r.gpu" 2>"$log/$r.gpu.err" || true
  faces=$(field "$log/$r.cpu" 3)
  tc=$(field "$log/$r.cpu" 9); tg=$(field "$log/$r.gpu" 9)
  pc=$(field "$log/$r.cpu" 11); pg=$(field "$log/$r.gpu" 11)
  err=$(field "$log/$r.gpu" 10)
  dev=$(sed -n 's/.*from the CPU result \([^ ]*\) %.*/\1/p' "$log/$r.gpu")
  ratio=$(awk -v c="${tc:-0}" -v g="${tg:-0}" 'BEGIN { if (c > 0 && g > 0) { if (g < c) printf "%.2fx faster", c / g; else printf "%.2fx slower", g / c } else print "failed" }')
  echo "| $name | ${faces:-?} | ${tc:-failed} | ${tg:-failed} | $ratio | ${pc:-} | ${pg:-} | ${err:-} | ${dev:-} |"
done
echo
echo "Cost proxies (host seconds per outer iteration without GPU waits, PCG iterations per shape solve, waits per PCG iteration, set-ups, bytes moved):"
for r in "${rows[@]}"; do grep -h "proxies" "$log/$r.cpu" "$log/$r.gpu" || echo "girths-homer-$r: no proxies (the run failed; see $log)"; done
if [ -x "$BIN/cholesky-bench" ]; then
  chol_rows=()
  for r in "${rows[@]}"; do case "$r" in 100k|1m) chol_rows+=("$r") ;; esac; done
  if [ ${#chol_rows[@]} -gt 0 ]; then
    echo
    echo "Cholesky preconditioner, one application (one lane per dot product against teams):"
    "$BIN/cholesky-bench" "${chol_rows[@]}" 2>"$log/cholesky.err" | grep -v '^adapter:' \
      || echo "cholesky-bench failed (see $log/cholesky.err)"
  fi
fi

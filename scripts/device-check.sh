#!/usr/bin/env bash
# One device call, everything in priority order, each step time-boxed so
# that what ran comes back: run from the repository root on the device
# machine, with .devbin (scripts/device-pack.sh) and .gl carried.
#   1. scripts/gpu-bench.sh 100k 1m (CPU and GPU rows, parity, proxies;
#      the Cholesky bench too with CHOLESKY=1), with debug logs;
#   1b. the 100k rows again, GPU then CPU: the driver's shader cache is
#      warm by then (step 1's GPU rows ran on a fresh machine);
#   1c. the 1.2M and 100k GPU rows with every factor made on the host by
#      faer (METRICDEFORM_GPU_FACTORIZATION=host), against step 1's made
#      on the GPU (the default on a hardware adapter, solver_gpu::factorize);
#   1d. the GPU factorization's kernels: the 1.2M and 100k GPU rows with
#      every long sum a lane an entry (METRICDEFORM_GPU_FACTOR_KERNELS=
#      entries, as before the tiles) and with tiles everywhere (=tiles),
#      against step 1's (each dispatch the faster by the model);
#   1e. the 1.2M and 100k GPU rows with glibc's own malloc settings
#      (MALLOC_MMAP_MAX_ at glibc's default), against the binaries' default
#      since this session's memory::keep_freed_memory (freed blocks kept for
#      reuse: no fresh pages to fault in for each vector over 32 MiB;
#      BENCHMARKS.md, "Host steps between the solves");
#   2. the conformance suite (the 1.2M parity test skipped: step 1 is that
#      check), then the kernels test binary twice at 16 threads, each under
#      a watchdog that dumps the threads' wait channels where it hangs (it
#      hung in 6 of 15 such runs on H200s before a1465b3's turns);
#   3. the 4.3M rows while time is left: GPU, GPU with every long sum of
#      its factorizations a lane an entry (as 1d), GPU with glibc's own
#      malloc settings (as 1e), CPU (over 110 s on the H200's host), then GPU with the
#      factors made on the host (its host peak against the default's:
#      those factors on the host);
#   3b. the host steps between the solves at 4.3M (benches/host_steps.rs)
#      on all the host's threads, then with glibc's own settings (as 1e);
#   4. with CHOLESKY_FACTOR=1, the host's Cholesky factorization of K at
#      1.2M faces, faer's loop against the elimination tree's subtrees at
#      once, on 1 thread and on all (benches/cholesky_factor.rs), and the
#      fill orderings at 1.2M (benches/fill_ordering.rs).
# END (seconds, default 540) bounds the whole; logs go to $OUT/logs.tgz and
# the table to $OUT/table.md.
set -u
T0=$(date +%s); el() { echo $(( $(date +%s) - T0 )); }
END=${END:-540}; left() { echo $(( END - $(el) )); }
# Runs "$@" for at most the time left (at most $CAP seconds where given);
# skipped where under 10 s are left (`timeout 0` would mean no limit).
bounded() {
  local t; t=$(left); [ -n "${CAP:-}" ] && [ "$CAP" -lt "$t" ] && t=$CAP
  [ "$t" -gt 10 ] || { echo "skipped (no time left): $1"; return 124; }
  timeout "$t" "$@"
}
R=$PWD; L=/tmp/devlog; mkdir -p "$L"
pack() { tar czf "$OUT/logs.tgz" -C /tmp devlog 2>/dev/null; }
for f in .gl/*.deb; do dpkg -x "$f" /; done; ldconfig
icd=/usr/local/nvidia/share/vulkan/icd.d/nvidia_icd.json
[ -f $icd ] && export VK_DRIVER_FILES=$icd
# The bench binaries read data/meshes under the path they were built in.
[ -d /work/main/data ] || { mkdir -p /work; ln -sfn "$R" /work/main; }
B=/tmp/bin; mkdir -p $B; tar xJf .devbin/bin.tar.xz -C $B
[ "${CHOLESKY:-0}" = 1 ] || rm -f $B/cholesky-bench
export RUST_LOG=${RUST_LOG:-info,metricdeform=debug,solver_gpu=debug}
{ nvidia-smi; lscpu | head -20; free -g; } > "$L/machine.txt" 2>&1
"$B/metricdeform" adapters | tee "$L/adapters.txt"
echo "== bench 100k 1m (t=$(el))"
LOG="$L" BIN=$B bounded "$R/scripts/gpu-bench.sh" 100k 1m 2>&1 | tee "$OUT/table.md"
pack
echo "== 100k again, the shader cache warm (t=$(el))"
for b in gpu cpu; do
  CAP=60 bounded "$B/pipeline-bench" --row girths-homer-100k per_constraint --backend $b --gpu-only \
    > "$L/100k.$b.warm" 2> "$L/100k.$b.warm.err"; echo "rc $?"
  grep -h '^| girths\|proxies' "$L/100k.$b.warm"
done
pack
echo "== the factors made on the host, 1.2M and 100k (t=$(el))"
for r in 1m 100k; do
  METRICDEFORM_GPU_FACTORIZATION=host CAP=120 bounded "$B/pipeline-bench" --row girths-homer-$r \
    per_constraint --backend gpu --gpu-only > "$L/$r.gpu.hostfactor" 2> "$L/$r.gpu.hostfactor.err"
  echo "rc $?"
  grep -h '^| girths\|proxies' "$L/$r.gpu.hostfactor"
done
pack
echo "== the factorization's kernels, 1.2M and 100k (t=$(el))"
for r in 1m 100k; do
  for k in entries tiles; do
    METRICDEFORM_GPU_FACTOR_KERNELS=$k CAP=60 bounded "$B/pipeline-bench" --row girths-homer-$r \
      per_constraint --backend gpu --gpu-only > "$L/$r.gpu.$k" 2> "$L/$r.gpu.$k.err"
    echo "$k rc $?"
    grep -h '^| girths\|proxies' "$L/$r.gpu.$k"
  done
done
pack
echo "== glibc's own malloc settings, 1.2M and 100k (t=$(el))"
# "$@" with glibc's own malloc settings: a MALLOC_ variable set by the user
# leaves them as they are (memory::keep_freed_memory); 65536 is glibc's own
# M_MMAP_MAX.
glibc() { MALLOC_MMAP_MAX_=65536 "$@"; }
for r in 1m 100k; do
  CAP=60 glibc bounded "$B/pipeline-bench" --row girths-homer-$r per_constraint \
    --backend gpu --gpu-only > "$L/$r.gpu.glibc" 2> "$L/$r.gpu.glibc.err"
  echo "rc $?"
  grep -h '^| girths\|proxies' "$L/$r.gpu.glibc"
done
pack
echo "== conformance (t=$(el))"
CAP=90 bounded "$B/conformance" --skip gpu_parity_at_a_million_faces_on_hardware > "$L/conformance-tests.txt" 2>&1
echo "rc $?"; tail -2 "$L/conformance-tests.txt"
pack
# Runs "$@" (a test binary) in the background, its output in $1. Still
# running after $WATCH seconds (a whole run takes under 10 s on an H200),
# it is stopped, and each thread's name, state, kernel wait channel,
# system call and kernel stack go to $1.threads first: the kernels binary hung in 5 of 13
# runs at 16 threads on the H200 (BENCHMARKS.md).
watched() {
  local out=$1; shift
  "$@" > "$out" 2>&1 & local p=$!
  local s=0
  while kill -0 $p 2>/dev/null && [ $s -lt "${WATCH:-30}" ]; do sleep 1; s=$((s + 1)); done
  if kill -0 $p 2>/dev/null; then
    echo "hung after $s s: $(grep -c ' ok$' "$out") tests finished"
    for t in /proc/$p/task/*; do
      # Name (spaces made _), state, kernel wait channel; then the system
      # call it sits in (202 futex: a lock; 16 ioctl: the driver; 7 poll)
      # and its kernel stack.
      echo "$(tr ' ' _ < $t/comm) $(awk '/^State/ {print $2}' $t/status) $(cat $t/wchan 2>/dev/null)"
      echo "    syscall $(cat $t/syscall 2>/dev/null)"
      cat $t/stack 2>/dev/null | head -8 | sed 's/^/    /'
    done > "$out.threads"
    grep -v '^    ' "$out.threads" | awk '{print $2, $3}' | sort | uniq -c | sort -rn | head
    kill -9 $p; wait $p 2>/dev/null; return 124
  fi
  wait $p
}
echo "== kernels tests, two runs at 16 threads under a watchdog (t=$(el))"
for i in 1 2; do
  [ "$(left)" -gt 70 ] || break
  # Since a1465b3 its tests take turns holding a device: slower than the
  # 7-8 s of a run at 16 threads before.
  WATCH=60 watched "$L/kernels-tests.$i.txt" "$B/kernels" --test-threads 16; echo "run $i rc $?"
  tail -2 "$L/kernels-tests.$i.txt"
done
pack
for b in gpu gpuentries gpuglibc cpu gpuhost; do
  echo "== 4m $b (t=$(el), left $(left))"
  [ "$(left)" -gt 60 ] || break
  f=; [ $b = gpuhost ] && f=host
  k=; [ $b = gpuglibc ] && k=glibc
  e=; [ $b = gpuentries ] && e=entries
  backend=gpu; [ $b = cpu ] && backend=cpu
  METRICDEFORM_GPU_FACTOR_KERNELS=$e METRICDEFORM_GPU_FACTORIZATION=$f $k bounded "$B/pipeline-bench" --row girths-homer-4m \
    per_constraint --backend $backend --gpu-only > "$L/4m.$b" 2> "$L/4m.$b.err"; echo "rc $?"
  grep -h '^| girths\|proxies' "$L/4m.$b"
  pack
done
echo "== host steps at 4.3M (t=$(el))"
CAP=90 bounded "$B/host-steps" 4m > "$L/host-steps.md" 2>&1; echo "rc $?"; cat "$L/host-steps.md"
CAP=90 glibc bounded "$B/host-steps" 4m > "$L/host-steps.glibc.md" 2>&1; echo "rc $?"
cat "$L/host-steps.glibc.md"
pack
if [ "${CHOLESKY_FACTOR:-0}" = 1 ]; then
  echo "== host Cholesky factorization at 1.2M (t=$(el))"
  REPEAT=1 CAP=100 bounded "$B/factor-bench" --1m 2> "$L/factor.err" | tee "$L/factor.md"
  CAP=60 bounded "$B/ordering-bench" --1m 2> "$L/ordering.err" | tee "$L/ordering.md"
  pack
fi
echo "== done t=$(el)"

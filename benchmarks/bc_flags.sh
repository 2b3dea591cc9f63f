#!/usr/bin/env bash
# The BC section of the bench (`benchmarks/bench.py`, the meta stage's one trainer) under each of several XLA
# flag sets, one process per set (XLA reads its flags when it starts). Each set's record goes to
# OUT/<set>.json with the flags it ran under (`xla_flags`, as every record made with XLA_FLAGS set);
# a set XLA refuses is reported and skipped. The BC loop is launch-bound (docs/decisions.md, BC):
# the sets are ways to run its small kernels with fewer launches or side by side.
#
#   benchmarks/bc_flags.sh [OUT]    (default OUT: runs/bc_flags)
#   PRESET=tiny benchmarks/bc_flags.sh runs/bc_flags_cpu   (a CPU smoke test of the script)
#   SETS="none graphs_concurrent" SET=meta.train.batch_size=256 benchmarks/bc_flags.sh OUT
#     (only those flag sets, each with a config change; its records are named <set>_<change>)
set -uo pipefail
out=${1:-runs/bc_flags}
buffers="--xla_gpu_enable_command_buffer=+WHILE,+CONDITIONAL"
declare -A sets=(
  [none]=""
  [graphs_concurrent]="$buffers --xla_gpu_graph_enable_concurrent_region=true"
  [graphs_concurrent_mode]="$buffers --xla_gpu_command_buffer_scheduling_mode=CONCURRENT"
  [triton_gemm]="--xla_gpu_triton_gemm_any=true"
  [graphs_concurrent_triton]="$buffers --xla_gpu_graph_enable_concurrent_region=true --xla_gpu_triton_gemm_any=true"
)
mkdir -p "$out"
change=()
[ -z "${SET:-}" ] || change=(--set "$SET")
for set in ${SETS:-none graphs_concurrent graphs_concurrent_mode triton_gemm graphs_concurrent_triton}; do
  [ -n "${sets[$set]+known}" ] || { echo "bc_flags.sh: no flag set named $set (known: ${!sets[*]})"; exit 2; }
  name=$set${SET:+_${SET//[^a-zA-Z0-9]/_}}
  echo "== $name: ${sets[$set]:-no flags} ${change[*]}"
  if XLA_FLAGS="${sets[$set]}" python -m benchmarks.bench --preset "${PRESET:-paper}" --backends warp \
      --skip scene experts gae brax filter tuning "${change[@]}" --out-dir "$out" \
      --record "$name" > "$out/$name.log" 2>&1; then
    python -c 'import json, sys; d = json.load(open(sys.argv[1]))
print("  " + ", ".join(f"{k}: {v:.0f} s" for k, v in d.items() if k.startswith("bc_") and k.endswith("wall_s")))' "$out/$name.json"
  else
    echo "  failed: $(tail -n 1 "$out/$name.log")"
  fi
done

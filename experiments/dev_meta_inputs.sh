#!/usr/bin/env bash
# The development comparison of what the meta-policies read (`meta.inputs`: unit, raw, centred;
# docs/decisions.md, "meta.inputs"), through experiments/dev_starting_kicks.sh's arms. For each
# development SEED: the paper preset's experts (the keep=chain starting kicks) with PPO cut to one
# update (a cheaper, weaker proxy: on seeds 102 and 103 they err 0.44-0.48 m, their starting kicks
# 0.34 m, the preset's experts after 625 updates about 0.33 m), then
# the nets cloned at the paper's BC budget once per input map from those same experts, and each
# filtered, all on the 110 development targets. Seeds and input maps run side by side (separate
# processes sharing the visible GPU: their kernels overlap only under CUDA MPS, started beforehand
# with `nvidia-cuda-mps-control -d`; without it they take turns); each arm's output in
# runs/dev_<arm>.log, its records in experiments/results/dev_starting_kicks/.
#
#   experiments/dev_meta_inputs.sh SEED [SEED ...]
#   PRIOR=runs/paper experiments/dev_meta_inputs.sh 102 103   (each arm starts from that run's
#        finished prior stage: no development knob touches the prior, so every arm would compute
#        the same one; a prior of another config is refused by the stage as stale)
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
base=start=long,spread,neighbour_leash=1,restarts=4,keep=chain,polish_generations=20,polish_sigma=0.25,paper_budget,ppo_updates=1
maps=(raw centred)
for seed in "$@"; do
  if ! [[ $seed =~ ^[0-9]+$ ]]; then echo "SEED must be a non-negative integer, got '$seed'" >&2; exit 2; fi
done
if [ -n "${PRIOR:-}" ] && [ ! -f "$PRIOR/prior/kick_prior.json" ]; then echo "PRIOR=$PRIOR: no finished prior in $PRIOR/prior" >&2; exit 2; fi
mkdir -p runs
# An arm's run directory, as dev_starting_kicks.sh names it (its parts with '=' and ',' as '_').
run_of() { echo "runs/dev_${1//[=,]/_}"; }
# One seed: the reference arm (unit) trains the experts, then every input map clones from them.
one_seed() {
  local ref="$base,seed=$1" arm pids=() failed=0
  for arm in "$ref" "${maps[@]/#/$ref,meta.inputs=}"; do
    if [ -n "${PRIOR:-}" ] && [ ! -d "$(run_of "$arm")/prior" ]; then
      mkdir -p "$(run_of "$arm")" && cp -r "$PRIOR/prior" "$(run_of "$arm")/prior"
    fi
  done
  STAGES=train-experts "$here/dev_starting_kicks.sh" "$ref" > "$(run_of "$ref").log" 2>&1 || return 1
  "$here/dev_starting_kicks.sh" "$ref" >> "$(run_of "$ref").log" 2>&1 & pids+=($!)
  for arm in "${maps[@]/#/$ref,meta.inputs=}"; do
    FROM="$ref" "$here/dev_starting_kicks.sh" "$arm" > "$(run_of "$arm").log" 2>&1 & pids+=($!)
  done
  for pid in "${pids[@]}"; do wait "$pid" || failed=1; done
  return $failed
}
pids=() failed=0
for seed in "$@"; do
  echo "seed $seed: $(run_of "$base,seed=$seed"){,_meta.inputs_raw,_meta.inputs_centred}.log"
  one_seed "$seed" & pids+=($!)
done
for pid in "${pids[@]}"; do wait "$pid" || failed=1; done
exit $failed

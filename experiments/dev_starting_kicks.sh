#!/usr/bin/env bash
# The development comparison of the experts' starting kicks (docs/decisions.md, "Experts"):
# each ARM trains the paper preset's experts at a short budget (25 PPO updates each) and the
# meta-policies (30,000 BC epochs) on development seeds (101), and scores the meta-policies
# unfiltered on 110 development targets halfway between the meta-test tasks. Never the meta-test
# seed or the held-out set. A part seed=<n> moves the seeds together (default 101). A part
# paper_budget trains at the paper preset's budget (625 PPO updates, 150,000 BC epochs) and adds
# the filtering stage on the same development targets and seed.
# Records land in runs/dev_<arm>/ (a finished stage is not rerun) and are copied after each stage to
# experiments/results/dev_starting_kicks/<arm>_{experts,table1,table2}_<device>.json. An arm that
# filtered ends with the targets it is judged by (`python -m experiments.family_targets`).
#
#   experiments/dev_starting_kicks.sh ARM [ARM ...]
#   STAGES=train-experts experiments/dev_starting_kicks.sh ARM ...   (the experts only: their
#        starting kicks' scores, before any net is trained)
#   GPUS=2 experiments/dev_starting_kicks.sh ARM ARM ...   (the arms side by side, one GPU each: MJX's
#        Warp runs on one GPU per process; each arm's output in runs/dev_<arm>.log)
#   EARLY_VERDICT=1 experiments/dev_starting_kicks.sh ARM ...   (a paper_budget arm whose experts
#        already miss their target stops there: the verdict is "missed" whatever the nets do, and
#        the meta and filtering stages' GPU time, about 8 minutes, is saved)
#   FROM=ARM experiments/dev_starting_kicks.sh ARM2 ...   (ARM2 starts from ARM's finished experts, copied
#        once into its own run directory: for arms that differ from ARM only in meta.* settings, e.g.
#        FROM=<arm> ... <arm>,meta.train.batch_size=256; any other difference and the experts stage refuses them as stale)
#   ARM: parts joined by commas, e.g. per_task (the reference alone) | neighbour_leash=<w> | generations=<n>
#        | repetitions=<n> (noisy kicks per CMA-ES candidate) | restarts=<n> (runs of the whole tuning, in one
#          batch; more than one: the runs' kicks chosen together with the neighbour leash)
#        | polish_generations=<n> (one more tuning from the chosen kicks) | env.<key>=<value> | meta.<key>=<value>
#        | long_start (every task starts from the prior's long kick at the strength where it rests nearest
#          its target) | seed=<n> | paper_budget (the preset's PPO and BC budgets, then filtering)
#        | ppo_updates=<n> (the experts' PPO cut to n updates: with paper_budget, nets cloned at the full
#          BC budget from cheap experts, for arms that differ in meta.* only; one update leaves them
#          about 0.1 m worse than their starting kicks)
#   (The records of arms this script no longer takes, e.g. family or start=long,spread, stay in
#   experiments/results/dev_starting_kicks/; docs/decisions.md says what they decided.)
set -euo pipefail
tasks=$(python3 -c 'print("[" + ",".join(f"{7.05 + 0.1 * i:.2f}" for i in range(110)) + "]")')
# The comparison's reference (arm per_task): every task from the best of its blended kick and the
# prior's anchors, tuned on its own; each arm's parts change it.
short_budget=(experts.ppo.total_env_steps=480000 experts.updates_per_chunk=25 meta.train.epochs=30000)
common=("meta.eval.tasks=$tasks" "filter.tasks=$tasks"
        experts.bc.per_task_strength=true experts.tune.anchor_starts=true experts.tune.neighbour_leash=0
        experts.tune.restarts=1 experts.tune.polish_generations=0)
# Copy the arm's finished records (experts, table1, table2) out of its run directory; called after
# every stage, so an arm stopped part way keeps the records of the stages it finished.
copy_records() {
  local run=$1 name=$2 device out=experiments/results/dev_starting_kicks
  [ -f "$run/experts/experts.json" ] || return 0
  # the device as the records' names give it: h100, h200, gpu or cpu
  device=$(python -c 'import json, sys; d = json.load(open(sys.argv[1]))["device"]
print(next((k.lower() for k in ("H100", "H200") if k in d), "cpu" if "cpu" in d.lower() else "gpu"))' "$run/experts/experts.json")
  mkdir -p "$out"
  cp "$run/experts/experts.json" "$out/${name}_experts_$device.json"
  for table in meta/table1 filter/table2; do
    if [ -f "$run/$table.json" ]; then cp "$run/$table.json" "$out/${name}_${table#*/}_$device.json"; fi
  done
}
# An arm's name in file names: its parts with '=' and ',' as '_'.
arm_name() { echo "${1//[=,]/_}"; }
gpus=${GPUS:-1}
if ! [[ $gpus =~ ^[1-9][0-9]*$ ]]; then echo "GPUS must be a positive integer, got '$gpus'" >&2; exit 2; fi
if (( gpus > 1 && $# > 1 )); then
  # Each GPU takes the next arm when its last one ends; every arm is this script run alone.
  mkdir -p runs
  pids=() failed=0 i=0
  for arm in "$@"; do
    gpu=$(( i % gpus ))
    if (( i >= gpus )); then wait "${pids[$gpu]}" || failed=1; fi
    log="runs/dev_$(arm_name "$arm").log"
    echo "arm $arm on GPU $gpu: $log"
    CUDA_VISIBLE_DEVICES=$gpu GPUS=1 "$0" "$arm" > "$log" 2>&1 &
    pids[$gpu]=$!
    i=$(( i + 1 ))
  done
  for pid in "${pids[@]}"; do wait "$pid" || failed=1; done
  for arm in "$@"; do tail -n 3 "runs/dev_$(arm_name "$arm").log"; done
  exit $failed
fi
for arm in "$@"; do
  seed=101
  sets=()
  budget=("${short_budget[@]}")
  stages=${STAGES:-train-experts meta-train}
  IFS=, read -ra parts <<< "$arm"
  for part in "${parts[@]}"; do
    case "$part" in
      per_task) ;;
      neighbour_leash=*|generations=*|repetitions=*|restarts=*|polish_generations=*) sets+=("experts.tune.$part") ;;
      long_start) sets+=(experts.bc.per_task_strength=false) ;;
      seed=*) seed=${part#seed=} ;;
      paper_budget) budget=(); stages=${STAGES:-train-experts meta-train filter} ;;
      ppo_updates=*) n=${part#ppo_updates=}  # n updates of the paper preset's 256 episodes x 75 steps, one chunk
        if ! [[ $n =~ ^[1-9][0-9]*$ ]]; then echo "ppo_updates must be a positive integer, got '$n'" >&2; exit 2; fi
        sets+=("experts.ppo.total_env_steps=$(( n * 256 * 75 ))" "experts.updates_per_chunk=$n") ;;
      env.*|meta.*) sets+=("$part") ;;  # an env or meta setting as it is, e.g. env.warp_contacts=<n>, meta.trainer=stacked
      *) echo "unknown arm part: $part" >&2; exit 2 ;;
    esac
  done
  seeds=(experts.eval.seed=$seed experts.tune.seed=$seed experts.seed=$seed meta.eval.seed=$seed filter.seed=$seed)
  name=$(arm_name "$arm")
  run="runs/dev_$name"
  if [ -n "${FROM:-}" ] && [ ! -d "$run/experts" ]; then
    src="runs/dev_$(arm_name "$FROM")/experts"
    if [ ! -f "$src/experts.json" ]; then echo "FROM=$FROM: no finished experts in $src" >&2; exit 2; fi
    mkdir -p "$run" && cp -r "$src" "$run/experts"
  fi
  for stage in $stages; do
    python -m bumps_jax "$stage" --preset paper --run-dir "$run" --set "${common[@]}" "${budget[@]}" "${seeds[@]}" "${sets[@]}"
    copy_records "$run" "$name"
    if [[ $stage == train-experts && ${EARLY_VERDICT:-0} == 1 && " $stages " == *" filter "* ]]; then
      # exit 1: a target already missed (the experts'); 2: the nets' targets not yet measured
      status=0; verdict=$(python -m experiments.family_targets --run-dir "$run") || status=$?
      if [ $status = 1 ]; then
        echo "$verdict"
        echo "$arm: the experts miss their target; meta and filtering not run (EARLY_VERDICT=1)"
        continue 2
      fi
    fi
  done
  # An arm that filtered: the targets it is judged by (docs/decisions.md), met or not.
  if [[ " $stages " == *" filter "* ]]; then python -m experiments.family_targets --run-dir "$run" || true; fi
done

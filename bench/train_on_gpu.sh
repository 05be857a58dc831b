#!/usr/bin/env bash
# The GPU training runs of issue 18 (configs/train_*gpu*.yaml), for a lent machine with one CUDA GPU
# and 16 cores, run from the repository root in short calls that must not lose the runs:
#
#   bash bench/train_on_gpu.sh start SECONDS PUGAN_DIR  # build the data with every core, time 3 steps
#                                                       # of each recipe (refusing slow ones), then start
#                                                       # the four runs detached, each stopping
#                                                       # (checkpoint and weights written) after SECONDS
#   bash bench/train_on_gpu.sh collect OUT              # wait until the runs end or ~9 minutes pass,
#                                                       # then pack each run's checkpoint, curves,
#                                                       # snapshots and log into OUT/gpu-NAME.tgz (one
#                                                       # archive per run: the files that come back
#                                                       # from a lent machine are limited in size)
#   bash bench/train_on_gpu.sh resume SECONDS PUGAN_DIR # continue from the committed checkpoints
#   bash bench/train_on_gpu.sh once SECONDS PUGAN_DIR OUT  # all of it in one call of SECONDS (a lent
#                                                       # machine's start costs minutes of its time)
#
# The runs share the GPU; each uses 4 CPU threads. Unpack the archive at the repository root.
set -u
# RECIPES (space-separated) picks runs; EXTRA adds arguments to each `python -m cadpu.train`.
# The LiDAR recipes and the held-out curves need Open3D (ray casting, point-to-surface): where the
# GPU machine lacks it, run the object recipes with EXTRA="--set curves_every=0" and score their
# snapshots with the curves afterwards on a machine that has it.
read -r -a RECIPE_LIST <<<"${RECIPES:-configs/train_lidar_gpu_alpha1.yaml configs/train_gpu.yaml configs/train_lidar_gpu.yaml configs/train_gpu_alpha1.yaml}"
read -r -a EXTRA_ARGS <<<"${EXTRA:-}"
PYTHON=${PYTHON:-python3}
LOGS=runs/gpu-logs

launch() {  # launch SECONDS PUGAN_DIR [--resume]
    mkdir -p "$LOGS"
    for recipe in "${RECIPE_LIST[@]}"; do
        name=$(basename "$recipe" .yaml)
        setsid nohup "$PYTHON" -m cadpu.train "$recipe" --max-seconds "$1" --curves-pugan "$2" ${3:-} "${EXTRA_ARGS[@]}" \
            >"$LOGS/$name.log" 2>&1 </dev/null &
        echo "$!" >"$LOGS/$name.pid"
    done
}

running() {
    local alive=0
    for pid in "$LOGS"/*.pid; do kill -0 "$(cat "$pid")" 2>/dev/null && alive=$((alive + 1)); done
    echo "$alive"
}

probe() {  # time 3 steps of each recipe from the shipped weights; fail when one takes > MAX_STEP_SECONDS
    # (a session once spent its GPU time on runs whose steps took 100 s, untimed beforehand)
    for recipe in "${RECIPE_LIST[@]}"; do
        rm -rf runs/probe
        "$PYTHON" -m cadpu.train "$recipe" --set steps=3 --set checkpoint_every=1 --set output=runs/probe \
            --set checkpoint=runs/probe/checkpoint.pt --set curves_every=0 --set snapshot_every=0 >/dev/null 2>&1 \
            || { echo "probe of $recipe failed"; return 1; }
        "$PYTHON" - "$recipe" "${MAX_STEP_SECONDS:-5}" <<'PY' || return 1
import csv, sys
seconds = [float(row["seconds"]) for row in csv.DictReader(open("runs/probe/log.csv"))]
step = seconds[-1] - seconds[0]  # the last two steps; the first carries the start-up
print(f"{sys.argv[1]}: {step / 2:.2f} s per step after the first")
sys.exit(step / 2 > float(sys.argv[2]))
PY
    done
    rm -rf runs/probe
}

collect() {  # collect OUT
    deadline=$((SECONDS + 540))
    while [ "$(running)" -gt 0 ] && [ $SECONDS -lt $deadline ]; do sleep 10; done
    echo "runs still going: $(running)"
    for recipe in "${RECIPE_LIST[@]}"; do
        name=$(basename "$recipe" .yaml)
        run=$("$PYTHON" -c "import sys; from pathlib import Path; from cadpu.train import Recipe
r = Recipe.from_yaml(Path(sys.argv[1])); print(r.output, r.checkpoint, r.curves_csv)" "$recipe")
        read -r output checkpoint curves <<<"$run"
        echo "== $name"; tr '\r' '\n' <"$LOGS/$name.log" | grep -v '^$' | tail -n 2
        tar czf "$1/gpu-$name.tgz" "$checkpoint" "$curves" "$output/log.csv" "$output/snapshots" \
            "$output"/*.pt* "$LOGS/$name.log" 2>/dev/null
    done
    ls -la "$1"
}

prepare() {  # the data, built once per spec with every core, and a timing of each recipe's steps
    nvidia-smi --query-gpu=name,memory.total --format=csv,noheader
    for recipe in "${RECIPE_LIST[@]}"; do
        "$PYTHON" -c "import sys; from pathlib import Path; from cadpu.data import load_or_build; from cadpu.train import Recipe
r = Recipe.from_yaml(Path(sys.argv[1])); print(sys.argv[1], len(load_or_build(r.data, Path(r.cache_dir), False, 16)), 'patches')" "$recipe"
    done
    probe || { echo "not started: a step is too slow or failed (MAX_STEP_SECONDS=${MAX_STEP_SECONDS:-5})"; return 1; }
}

case "${1:-}" in
start | resume)
    prepare || exit 1
    launch "$2" "$3" "$([ "$1" = resume ] && echo --resume)"
    sleep 60
    tail -n 3 "$LOGS"/*.log
    ;;
collect)
    collect "$2"
    ;;
once)
    # SECONDS is the whole call's: the runs get what the data and the probe leave, less 60 s for
    # their last checkpoint and the archives.
    prepare || exit 1
    left=$(($2 - SECONDS - 60))
    [ "$left" -gt 30 ] || { echo "no time left to train ($left s)"; exit 1; }
    echo "training for $left s"
    launch "$left" "$3"
    collect "$4"
    ;;
*)
    echo "usage: $0 start SECONDS PUGAN_DIR | resume SECONDS PUGAN_DIR | collect OUT | once SECONDS PUGAN_DIR OUT" >&2
    exit 2
    ;;
esac

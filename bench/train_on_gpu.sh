#!/usr/bin/env bash
# The GPU training runs of issue 18 (configs/train_*gpu*.yaml), for a lent machine with one CUDA GPU
# and 16 cores, run from the repository root in short calls that must not lose the runs:
#
#   bash bench/train_on_gpu.sh start SECONDS PUGAN_DIR  # build the data with every core, time 3 steps
#                                                       # of each recipe (refusing slow ones), then start
#                                                       # the four runs detached, each stopping
#                                                       # (checkpoint and weights written) after SECONDS
#   bash bench/train_on_gpu.sh collect OUT              # wait until the runs end or ~9 minutes pass,
#                                                       # then pack checkpoints, curves, snapshots and
#                                                       # logs into OUT/gpu-runs.tgz
#   bash bench/train_on_gpu.sh resume SECONDS PUGAN_DIR # continue from the committed checkpoints
#
# The runs share the GPU; each uses 4 CPU threads. Unpack the archive at the repository root.
set -u
# RECIPES (space-separated) picks runs; EXTRA adds arguments to each `python -m cadpu.train`.
# The LiDAR recipes and the held-out curves need Open3D (ray casting, point-to-surface): where the
# GPU machine lacks it, run the object recipes with EXTRA="--set curves_every=0" and score their
# snapshots with the curves afterwards on a machine that has it.
read -r -a RECIPES <<<"${RECIPES:-configs/train_lidar_gpu_alpha1.yaml configs/train_gpu.yaml configs/train_lidar_gpu.yaml configs/train_gpu_alpha1.yaml}"
read -r -a EXTRA <<<"${EXTRA:-}"
PYTHON=${PYTHON:-python3}
LOGS=runs/gpu-logs

launch() {  # launch SECONDS PUGAN_DIR [--resume]
    mkdir -p "$LOGS"
    for recipe in "${RECIPES[@]}"; do
        name=$(basename "$recipe" .yaml)
        setsid nohup "$PYTHON" -m cadpu.train "$recipe" --max-seconds "$1" --curves-pugan "$2" ${3:-} "${EXTRA[@]}" \
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
    for recipe in "${RECIPES[@]}"; do
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

case "${1:-}" in
start | resume)
    nvidia-smi --query-gpu=name,memory.total --format=csv,noheader
    # One cache per data spec, made once with every core before the runs read it.
    for recipe in "${RECIPES[@]}"; do
        "$PYTHON" -c "import sys; from pathlib import Path; from cadpu.data import load_or_build; from cadpu.train import Recipe
r = Recipe.from_yaml(Path(sys.argv[1])); print(sys.argv[1], len(load_or_build(r.data, Path(r.cache_dir), False, 16)), 'patches')" "$recipe"
    done
    probe || { echo "not started: a step is too slow or failed (MAX_STEP_SECONDS=${MAX_STEP_SECONDS:-5})"; exit 1; }
    launch "$2" "$3" "$([ "$1" = resume ] && echo --resume)"
    sleep 60
    tail -n 3 "$LOGS"/*.log
    ;;
collect)
    deadline=$((SECONDS + 540))
    while [ "$(running)" -gt 0 ] && [ $SECONDS -lt $deadline ]; do sleep 10; done
    echo "runs still going: $(running)"
    for log in "$LOGS"/*.log; do echo "== $log"; tr '\r' '\n' <"$log" | grep -v '^$' | tail -n 2; done
    tar czf "$2/gpu-runs.tgz" cadpu/checkpoints/*_gpu.* runs/train/*_gpu/log.csv runs/train/*_gpu/snapshots \
        runs/train/*_gpu/generator.pt* "$LOGS"/*.log 2>/dev/null
    ls -la "$2"
    ;;
*)
    echo "usage: $0 start SECONDS PUGAN_DIR | resume SECONDS PUGAN_DIR | collect OUT" >&2
    exit 2
    ;;
esac

#!/usr/bin/env bash
# One lent-GPU call for the new world (docs/experiments/streets_as_hard.md, "A network trained on
# the new world"): the training rule's fine-tune (gpu_world_train.sh, 3 epochs from squeezeseg-v4,
# the bundled network when it ran (INIT overrides), on the places world with the per-class return
# model) and the paper's real + synthetic and synthetic arms
# (augment_experiment.py, both channel sets, seeds 0-2) run at once, then packed into $OUT as
# at most 8 files. Stops itself at $LIMIT seconds so that whatever finished still comes back.
#
# Before the call, here (the tracked weights are 56 MB of the 64 MiB a call may carry):
#   python research/experiments/augment_experiment.py --pack $SEMANTICKITTI --out .gpu/packed
#   (.whl/: trimesh, embreex and nlopt wheels for Python 3.12, see gpu_world_train.sh)
#   every models/weights file but squeezeseg.* removed from the work tree for the call only
#   (git checkout -- models/weights afterwards)
# The run call: command `bash research/experiments/gpu_new_world.sh`, carry [".whl", ".gpu"],
# timeout_s 600.
# Local dry run (CPU, tiny): FALSIFY_DRY=1 OUT=/tmp/nw-dry bash research/experiments/gpu_new_world.sh
#
# What comes back: epoch{1,2,3}.tar (adjusted .pt, ONNX + sidecar, adjust JSON of that epoch),
# augment-results.json, logs.tar.gz (both pipelines' logs, the train log, timings).
set -uo pipefail
export PYTHONUNBUFFERED=1
ROOT=$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)
DRY=${FALSIFY_DRY:-0}
: "${OUT:?set OUT (the device machine sets it)}"
FINAL=$OUT
LIMIT=${LIMIT:-500}
W=${W:-/tmp/new-world}
rm -rf "$W"; mkdir -p "$W/wout" "$W/aug" "$W/logs" "$FINAL"
if [[ $DRY == 1 ]]; then
    PY=python3; STEPS=2; SEEDS=0; PAR=2; SCANS=8; DEVICE=cpu; LIMIT=400
    BASE=/tmp/falsify-dry/work; SITE=/tmp/falsify-dry/site   # gpu_world_train.sh's dry paths
else
    if [[ -x /opt/torch/.venv/bin/python3 ]]; then PY=/opt/torch/.venv/bin/python3; else PY=python3; fi
    STEPS=1200; SEEDS=0,1,2; PAR=12; SCANS=2000; DEVICE=cuda
    BASE=/tmp/gpu-world; SITE=/tmp/site
fi
T0=$(date +%s)
log() { echo "== [$(($(date +%s) - T0)) s] $*" | tee -a "$W/logs/timings.txt"; }

# 1. the fine-tune: gpu_world_train.sh installs the wheels and falsify under $SITE, $SITE-falsify
(
    # the weights the rule fine-tunes: the bundled network when it ran, kept as squeezeseg-v4
    export OUT=$W/wout BASE SITE PY DEVICE INIT=${INIT:-models/weights/squeezeseg-v4.pt}
    [[ $DRY == 1 ]] && export FALSIFY_DRY=1 OUT=$W/wout
    timeout "$LIMIT" bash "$ROOT/research/experiments/gpu_world_train.sh" \
        configs/worlds/semantickitti-places.json 41 42 3
) > "$W/logs/world.log" 2>&1 &
WORLD=$!
log "world pipeline started (pid $WORLD)"

# 2. the augment arms, once falsify is installed: their synthetic set, then 12 runs at once
until grep -q "install:" "$BASE/logs/timings.txt" 2> /dev/null || ! kill -0 $WORLD 2> /dev/null; do
    sleep 2
done
log "falsify installed"
if [[ $DRY == 1 ]]; then P=$SITE-falsify; else P=$SITE-falsify:$SITE; fi
(
    export PYTHONPATH=$P
    cd "$W"   # not the repo root: ./falsify there would shadow the installed package
    left=$((LIMIT - ($(date +%s) - T0)))
    timeout "$left" bash -c "
        OMP_NUM_THREADS=1 '$PY' -m falsify dataset '$ROOT/configs/paper.toml' --scans $SCANS \
            --seed 1 --first-background 1000 --backgrounds 250 --workers 8 --out '$W/syn' --json \
            > '$W/aug/synthetic-set.json' &&
        '$PY' '$ROOT/research/experiments/augment_experiment.py' --fit '$ROOT/.gpu/packed/fit.npz' \
            --eval '$ROOT/.gpu/packed/eval.npz' --synthetic '$W/syn' --out '$W/aug' \
            --arms real+synthetic,synthetic --seeds $SEEDS --steps $STEPS --batch 16 \
            --device $DEVICE --parallel $PAR"
) > "$W/logs/augment.log" 2>&1 &
AUG=$!
log "augment started (pid $AUG)"
wait $AUG; log "augment exit $?"
wait $WORLD; log "world exit $?"

# 3. pack: one tar per epoch (each < 16 MiB), the augment results, every log
WORK=$(ls -d "$BASE"/semantickitti-places-s41-v42 2> /dev/null)
for e in 1 2 3; do
    files=()
    for f in "epoch$e-adjusted.pt" "adjust-epoch$e.json" "epoch$e/squeezeseg.onnx" "epoch$e/squeezeseg.json"; do
        [[ -n $WORK && -f $WORK/$f ]] && files+=("$f")
    done
    ((${#files[@]})) && tar -cf "$FINAL/epoch$e.tar" -C "$WORK" "${files[@]}"
done
[[ -f $W/aug/results.json ]] && cp "$W/aug/results.json" "$FINAL/augment-results.json"
cp "$W/aug/synthetic-set.json" "$W/logs/" 2> /dev/null
[[ -n $WORK ]] && cp "$WORK/model/train_log.jsonl" "$W/logs/" 2> /dev/null
[[ -d $BASE/logs ]] && cp -r "$BASE/logs" "$W/logs/world-logs"
tar -czf "$FINAL/logs.tar.gz" -C "$W" logs
log "packed"
ls -la "$FINAL"
tail -n 20 "$W/logs/augment.log"
tail -n 5 "$W/logs/world.log"

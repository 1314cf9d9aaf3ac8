#!/usr/bin/env bash
# Fitted-world training on a lent GPU machine: the same recipe as research/experiments/
# fitted_world.py (its train/val dataset arguments, its fine-tune recipe, one epoch at a time with
# each epoch's checkpoint kept, the logit adjustment on synthetic validation, the ONNX export),
# with the datasets written by 16 processes and the training on CUDA. The fit/evaluation-split
# predictions (real SemanticKITTI, not on that machine) stay local.
#
# The run call (from the repo root; the wheels in .whl/ travel by carry):
#   command: bash research/experiments/gpu_world_train.sh configs/worlds/semantickitti-fit-parked.json 31 32
#   carry:   [".whl"]
#   timeout_s: 480
# (args: PROFILE TRAIN_SEED VAL_SEED [EPOCHS=1] [SCANS=4000], fitted_world.py's defaults; env:
#  INIT=models/weights/X.pt, default squeezeseg-v1.pt as fitted_world.py's --init default; its
#  parked run (seeds 31 32) used squeezeseg.pt: prefix the command with
#  INIT=models/weights/squeezeseg.pt. Also LR, LR_DECAY, BATCH, VAL_SCANS, ALPHAS, WORKERS;
#  ADJUST=gpu|cli|0; REUSE_DATA=1 on a rerun on the same warm machine keeps its datasets.)
# Expected on the device (estimated from this 2-core CPU, not measured there): install ~15 s,
# 4000 + 400 scans on 16 processes ~1 min (0.13 s a scan a core here), one epoch on CUDA with
# validation ~1 min, adjust + export ~30 s: ~3-4 min. Every stage prints its seconds.
#
# What comes back in $OUT (flat, at most 8 files, each < 16 MiB), for the last epoch E:
#   epochE-checkpoint.pt (11 MB: model + optimiser, what `--resume` and fitted_world.py take)
#   adjust-epochE.json  epochE-adjusted.pt  epochE-squeezeseg.onnx  epochE-squeezeseg.json
#   train_log.jsonl (one line an epoch: loss, val car IoU, precision bf16/fp32, seconds)
#   logs.tar.gz (every step's output, timings.txt, versions.txt) and, with EPOCHS > 1,
#   earlier-epochs.tar (epoch<e>/squeezeseg.{onnx,json}, adjust-epoch<e>.json of the earlier
#   epochs, in fitted_world.py's work-folder layout).
# $OUT is refreshed after every stage and on any exit, so a run stopped by its time limit or
# failing still brings back its logs and newest checkpoint.
# In fitted_world.py's work folder: epochE-checkpoint.pt, adjust-epochE.json and
# epochE-adjusted.pt keep their names; epochE-squeezeseg.{onnx,json} are epochE/squeezeseg.*.
# (fitted_world.py itself still calls `python -m falsify.models.train/adjust/export`, which have
# no command line since the CLI split; this script uses `falsify train/adjust/export`.)
#
# Local dry run (CPU, tiny; python3 here already has every dependency, so no wheels):
#   FALSIFY_DRY=1 bash research/experiments/gpu_world_train.sh configs/worlds/semantickitti-fit-parked.json 31 32
# (16 training scans, 8 validation scans, 1 epoch, --device cpu, 2 workers,
#  OUT=/tmp/falsify-dry/out; ~85 s here)
set -euo pipefail
export PYTHONUNBUFFERED=1

if [[ $# -lt 3 ]]; then
    echo "usage: $0 PROFILE TRAIN_SEED VAL_SEED [EPOCHS] [SCANS]" >&2
    exit 2
fi
ROOT=$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)
PROFILE=$(cd "$ROOT" && realpath "$1")
TRAIN_SEED=$2
VAL_SEED=$3
DRY=${FALSIFY_DRY:-0}

# fitted_world.py's defaults
EPOCHS=${4:-1}
SCANS=${5:-4000}                 # training scans, backgrounds 1000.. (625)
VAL_SCANS=${VAL_SCANS:-400}      # validation scans, backgrounds 5000.. (50)
INIT=$(cd "$ROOT" && realpath "${INIT:-models/weights/squeezeseg-v1.pt}")
LR=${LR:-1.5e-4}
LR_DECAY=${LR_DECAY:-0.7}
BATCH=${BATCH:-8}
ALPHAS=${ALPHAS:-0,0.25,0.5,0.6,0.65,0.7,0.75,0.8,0.85,0.9,1.0}
ADJUST=${ADJUST:-gpu}            # gpu | cli | 0 (0: stop after training: no adjust, no export)

# the device machine's torch venv (python3 there is said to be it; this does not rely on PATH)
if [[ -z ${PY:-} ]]; then
    if [[ $DRY != 1 && -x /opt/torch/.venv/bin/python3 ]]; then PY=/opt/torch/.venv/bin/python3; else PY=python3; fi
fi
DEVICE=${DEVICE:-cuda}
WORKERS=${WORKERS:-16}
BASE=${BASE:-/tmp/gpu-world}
SITE=${SITE:-/tmp/site}
if [[ $DRY == 1 ]]; then
    SCANS=${5:-16}; VAL_SCANS=8; EPOCHS=${4:-1}; DEVICE=cpu; WORKERS=2
    BASE=/tmp/falsify-dry/work; SITE=/tmp/falsify-dry/site; OUT=${OUT:-/tmp/falsify-dry/out}
    rm -rf "$OUT"
fi
: "${OUT:?set OUT (the device machine sets it)}"
mkdir -p "$OUT" "$BASE"
WORK=$BASE/$(basename "$PROFILE" .json)-s$TRAIN_SEED-v$VAL_SEED
MODEL=$WORK/model
LOGS=$BASE/logs
# nothing of an earlier call on a warm machine is kept (REUSE_DATA=1: its datasets, where they
# were made with the same arguments; not after a code change that alters the scenes)
rm -rf "$LOGS" "$MODEL" "$WORK"/epoch* "$WORK"/adjust-epoch*; mkdir -p "$WORK" "$LOGS"
TIMES=$LOGS/timings.txt
T0=$(date +%s); LAST=$T0
# $OUT holds what is done so far after every stage (and on any exit): a run killed at its time
# limit or failing still brings back its logs and newest checkpoint. Flat names, <= 8 files.
snapshot() {
    [[ -f $MODEL/train_log.jsonl ]] && cp "$MODEL/train_log.jsonl" "$OUT/"
    tar -czf "$OUT/logs.tar.gz" -C "$BASE" logs
}
trap 'rc=$?; echo "== exit $rc after $(($(date +%s) - T0)) s" | tee -a "$TIMES"; snapshot || true' EXIT
stage() {   # stage NAME: the seconds since the previous stage, and since the start
    local now; now=$(date +%s)
    echo "== [$(date -u +%H:%M:%S)] $1: +$((now - LAST)) s (total $((now - T0)) s)" | tee -a "$TIMES"
    LAST=$now
    snapshot
}
echo "profile=$PROFILE train_seed=$TRAIN_SEED val_seed=$VAL_SEED epochs=$EPOCHS scans=$SCANS" \
     "val_scans=$VAL_SCANS init=$INIT lr=$LR lr_decay=$LR_DECAY batch=$BATCH device=$DEVICE" \
     "workers=$WORKERS dry=$DRY" | tee -a "$TIMES"

# 1. the packages the machine lacks (trimesh, embreex, nlopt: .whl/, carried), then falsify itself
#    built from this copy of the tree (a clean copy: no stale build/ of an earlier call).
#    Without pip in the venv (a venv made by uv has none) the wheels are unpacked (none of them
#    has a .data folder, so that is the same) and the tree is copied as below.
HAVE_PIP=1; "$PY" -m pip --version > /dev/null 2>&1 || HAVE_PIP=0
if [[ $DRY != 1 ]]; then
    if [[ $HAVE_PIP == 1 ]]; then
        "$PY" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
            --target "$SITE" "$ROOT"/.whl/*.whl
    else
        echo "WARNING: no pip for $PY: unpacking the wheels into $SITE" >&2
        mkdir -p "$SITE"
        for w in "$ROOT"/.whl/*.whl; do "$PY" -m zipfile -e "$w" "$SITE"; done
    fi
fi
SRC=$BASE/src
rm -rf "$SRC" "$SITE-falsify"; mkdir -p "$SRC"
tar -C "$ROOT" --exclude=./.git --exclude=./.whl --exclude=./runs --exclude=./build \
    --exclude=./data --exclude=./out --exclude='*.egg-info' --exclude=__pycache__ -cf - . \
    | tar -C "$SRC" -xf -
if [[ $HAVE_PIP == 0 ]] || ! "$PY" -m pip install -q --no-index --no-deps --no-build-isolation \
        --no-compile --no-cache-dir --target "$SITE-falsify" "$SRC" > "$LOGS/pip-falsify.log" 2>&1; then
    # the same layout by hand (pyproject's package-dir: sampler, models, reports, configs
    # install as falsify.*)
    echo "WARNING: pip could not build falsify (see logs/pip-falsify.log); copying the tree" >&2
    tail -5 "$LOGS/pip-falsify.log" >&2 2> /dev/null || true
    rm -rf "$SITE-falsify"; mkdir -p "$SITE-falsify"
    cp -r "$SRC/falsify" "$SITE-falsify/falsify"
    for d in sampler models reports configs; do cp -r "$SRC/$d" "$SITE-falsify/falsify/$d"; done
fi
if [[ $DRY == 1 ]]; then P=$SITE-falsify; else P=$SITE-falsify:$SITE; fi
export PYTHONPATH=$P${PYTHONPATH:+:$PYTHONPATH}
# one thread per dataset process (16 processes on 16 cores); deterministic cuBLAS
export OMP_NUM_THREADS=1 MKL_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1
export CUBLAS_WORKSPACE_CONFIG=:4096:8
# every command runs outside the repo: `python -m falsify` there would import ./falsify (the bare
# source folder, without falsify.models) instead of the installed package
cd "$BASE"
# what this flow needs must import; nlopt (falsify's samplers only) may not
"$PY" - <<'EOF' 2>&1 | tee "$LOGS/versions.txt"
import importlib
import sys
print("python", sys.version.split()[0], sys.executable)
for m in ("numpy", "scipy", "pandas", "onnx", "onnxruntime", "embreex", "torch",
          "falsify", "nlopt"):
    try:
        mod = importlib.import_module(m)
    except Exception as exc:
        if m != "nlopt":
            raise
        print(f"WARNING: nlopt does not import ({exc}); not needed here")
        continue
    print(f"{m:12s} {getattr(mod, '__version__', '?'):14s} {getattr(mod, '__file__', '')}")
import falsify.models.train, falsify.sensor.raycast, falsify.world.profile  # noqa: E401,F401
import torch
print("cuda", torch.cuda.is_available(),
      torch.cuda.get_device_name(0) if torch.cuda.is_available() else "")
EOF
[[ $DEVICE != cuda ]] || nvidia-smi --query-gpu=name,memory.used,memory.total --format=csv || true
stage install

# 2. the profiled training and validation sets (fitted_world.py's dataset arguments)
dataset() {   # dataset OUT SCANS SEED FIRST BACKGROUNDS NAME
    local args=(--scans "$2" --seed "$3" --first-background "$4" --backgrounds "$5"
                --world "$PROFILE")
    if [[ ${REUSE_DATA:-0} == 1 && -f $1.args && $(cat "$1.args") == "${args[*]}" ]]; then
        echo "$6: reusing $1 (REUSE_DATA=1, same arguments)"
    else
        rm -rf "$1" "$1.args"
        "$PY" -m falsify dataset "$ROOT/configs/paper.toml" "${args[@]}" --out "$1" \
            --workers "$WORKERS" --json > "$LOGS/dataset-$6.json"
        echo "${args[*]}" > "$1.args"
    fi
    echo "$6: $(find "$1" -name '*.npy' | wc -l) scans, $(du -sh "$1" | cut -f1)"
}
dataset "$WORK/train" "$SCANS" "$TRAIN_SEED" 1000 625 train
stage "dataset train ($SCANS scans)"
dataset "$WORK/val" "$VAL_SCANS" "$VAL_SEED" 5000 50 val
stage "dataset val ($VAL_SCANS scans)"
unset OMP_NUM_THREADS MKL_NUM_THREADS OPENBLAS_NUM_THREADS

# 3. the fine-tune, one epoch at a time (each epoch's checkpoint kept), then per epoch the logit
#    adjustment chosen on the synthetic validation set and the ONNX export
# `falsify adjust` runs on the CPU with 2 torch threads: ~3 s a validation scan on a 2-core CPU,
# minutes for 400 scans. ADJUST=gpu (default) runs its choose_alpha on $DEVICE instead, the same
# steps with the module's own pieces, fp32 (no TF32), and writes what `falsify adjust --json`
# writes (checked equal to it on the CPU by the dry run); ADJUST=cli runs `falsify adjust`.
cat > "$BASE/adjust_on_device.py" <<'EOF'
import json
import sys
from dataclasses import asdict
from pathlib import Path

import numpy as np
import torch

import falsify.models.adjust as A
from falsify.classes import CAR
from falsify.models.spec import DEFAULT_CHANNELS
from falsify.models.squeezeseg import SqueezeSeg, load_state
from falsify.models.train import batch_tensors, list_scans, load_scan
from falsify.results.metrics import class_scores, confusion

weights, val, out, alphas_text, device = sys.argv[1:6]
torch.backends.cudnn.allow_tf32 = False
torch.backends.cuda.matmul.allow_tf32 = False
alphas = sorted(set(float(a) for a in alphas_text.split(",") if a.strip()))
state = load_state(weights)
files = list_scans(val, "--val")
model = SqueezeSeg(DEFAULT_CHANNELS, crf_iterations=3)
model.load_state_dict(state)
model.eval().to(device)
counts = np.zeros((len(alphas), 4, 3), np.int64)
with torch.inference_mode():
    for i in range(0, len(files), A.BATCH):
        scans = np.stack([load_scan(f) for f in files[i:i + A.BATCH]])
        x, xyz, mask, labels = batch_tensors(scans, DEFAULT_CHANNELS)
        x, xyz, mask = (t.to(device) for t in (x, xyz, mask))
        logits = model.backbone(x)
        invalid = scans[..., 4] <= 0
        for k, a in enumerate(alphas):
            off = torch.tensor(A.logit_offsets(a), dtype=logits.dtype).view(1, -1, 1, 1)
            pred = model.crf(logits + off.to(device), xyz, mask).argmax(1).cpu().numpy()
            pred[invalid] = 0
            counts[k] += confusion(pred, labels.numpy())
if counts[0, CAR, 0] + counts[0, CAR, 2] == 0:
    sys.exit(f"--val {val}: no car points, so car IoU cannot choose alpha")
scores = []
for a, c in zip(alphas, counts, strict=True):
    cls = class_scores(c)
    car = cls[CAR]
    scores.append(A.AlphaScore(a, car.iou, car.precision, car.recall, [x.iou for x in cls]))
best = max(scores, key=lambda s: (s.car_iou, -s.alpha))
result = A.Adjustment(str(val), len(files), best.alpha, scores)
out = Path(out)
tmp = out.with_suffix(".tmp")
torch.save(A.adjust_state(state, result.chosen), tmp)
tmp.replace(out)
print(json.dumps({**asdict(result), "out": str(out)}, indent=1))
EOF
adjust() {   # adjust EPOCH: epochE-adjusted.pt and adjust-epochE.json, as fitted_world.py names them
    if [[ $ADJUST == cli ]]; then
        "$PY" -m falsify adjust "$WORK/epoch$1-checkpoint.pt" --val "$WORK/val" \
            --out "$WORK/epoch$1-adjusted.pt" --alphas "$ALPHAS" --json > "$WORK/adjust-epoch$1.json"
    else
        "$PY" "$BASE/adjust_on_device.py" "$WORK/epoch$1-checkpoint.pt" "$WORK/val" \
            "$WORK/epoch$1-adjusted.pt" "$ALPHAS" "$DEVICE" > "$WORK/adjust-epoch$1.json"
    fi
}
for ((e = 1; e <= EPOCHS; e++)); do
    if [[ -f $MODEL/checkpoint.pt ]]; then start=(--resume); else start=(--init "$INIT"); fi
    "$PY" -m falsify train --data "$WORK/train" --out "$MODEL" --epochs "$e" \
        --val-data "$WORK/val" --no-export --lr "$LR" --lr-decay "$LR_DECAY" --batch "$BATCH" \
        --device "$DEVICE" "${start[@]}" 2>&1 | tee "$LOGS/train-epoch$e.log"
    cp "$MODEL/checkpoint.pt" "$WORK/epoch$e-checkpoint.pt"
    rm -f "$OUT"/epoch*-* "$OUT"/adjust-epoch*   # only the newest epoch's files, flat
    cp "$WORK/epoch$e-checkpoint.pt" "$OUT/"
    stage "train epoch $e"
    if [[ $ADJUST != 0 ]]; then
        # not fatal: the checkpoint comes back even if this fails (then adjust locally, on the
        # validation set regenerated with the same arguments)
        if adjust "$e" 2> "$LOGS/adjust-epoch$e.err"; then
            grep -E '"chosen"' "$WORK/adjust-epoch$e.json" || true
            cp "$WORK/adjust-epoch$e.json" "$LOGS/"
            cp "$WORK/adjust-epoch$e.json" "$WORK/epoch$e-adjusted.pt" "$OUT/"
            if "$PY" -m falsify export "$WORK/epoch$e-adjusted.pt" \
                    --out "$WORK/epoch$e/squeezeseg.onnx" 2> "$LOGS/export-epoch$e.err"; then
                cp "$WORK/epoch$e/squeezeseg.onnx" "$OUT/epoch$e-squeezeseg.onnx"
                if [[ -f $WORK/epoch$e/squeezeseg.json ]]; then
                    cp "$WORK/epoch$e/squeezeseg.json" "$OUT/epoch$e-squeezeseg.json"
                fi
            else
                echo "WARNING: export of epoch $e failed (export it locally):" >&2
                tail -5 "$LOGS/export-epoch$e.err" >&2
                rm -rf "$WORK/epoch$e"
            fi
        else
            echo "WARNING: adjust of epoch $e failed:" >&2; tail -5 "$LOGS/adjust-epoch$e.err" >&2
            rm -f "$WORK/epoch$e-adjusted.pt" "$WORK/adjust-epoch$e.json"
        fi
        stage "adjust + export epoch $e"
    fi
done

# 4. $OUT (the last epoch's files are there already): the earlier epochs' ONNX models
E=$EPOCHS
if [[ $ADJUST != 0 ]]; then
    if ((E > 1)); then
        earlier=(); have=0
        for ((e = E - 1; e >= 1; e--)); do   # newest first, while the tar stays < 15 MiB
            [[ -f $WORK/adjust-epoch$e.json && -f $WORK/epoch$e/squeezeseg.onnx ]] || continue
            add=$(cat "$WORK/epoch$e"/squeezeseg.{onnx,json} "$WORK/adjust-epoch$e.json" | wc -c)
            ((have + add < 15 * 1024 * 1024)) || { echo "earlier-epochs.tar: epoch $e and before left out"; break; }
            have=$((have + add))
            earlier+=("epoch$e/squeezeseg.onnx" "epoch$e/squeezeseg.json" "adjust-epoch$e.json")
        done
        if ((${#earlier[@]})); then tar -cf "$OUT/earlier-epochs.tar" -C "$WORK" "${earlier[@]}"; fi
    fi
fi
stage "collect"
for f in "$OUT"/*; do
    size=$(stat -c %s "$f")
    ((size < 16 * 1024 * 1024)) || echo "WARNING: $f is $size bytes, over 16 MiB: it will not come back" >&2
done
ls -la "$OUT"
echo "files in OUT: $(ls "$OUT" | wc -l) (at most 8 come back)"
tail -n 3 "$MODEL/train_log.jsonl"

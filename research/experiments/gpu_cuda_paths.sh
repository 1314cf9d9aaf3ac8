#!/usr/bin/env bash
# falsify's CUDA paths on one lent GPU call (docs/scale-out.md, "Measured on a lent NVIDIA
# H200"): the GPU-gated tests, then grid, predict, bench pipeline and train on cuda against the
# same on the CPU, every figure packed into $OUT/gpu.tar.gz.
#
# Before the call, here: .whl/ holds the trimesh, embreex and nlopt wheels for the device's
# Python (see gpu_world_train.sh); SK names a SemanticKITTI root of a few fit-split scans copied
# into the repository (e.g. .dev/sk: sequences 05 and 07, two scans each); models/weights files
# other than squeezeseg.*, squeezeseg20.* and pointnet20.pt are moved out for the call (the tree
# may carry 64 MiB) and put back after it. The call: command `SK=.dev/sk bash
# research/experiments/gpu_cuda_paths.sh`, carry [".whl", ".dev"], timeout_s 560 (it took 300 s
# on an H200 with 16 cores).
# Rehearsal on a CPU: DEV=cpu W=2 CFG=configs/smoke.toml BN=24 SN=16 SKIP_INSTALL=1 OUT=/tmp/g \
#   SK=DIR bash research/experiments/gpu_cuda_paths.sh
set -u
export PYTHONUNBUFFERED=1
R=${OUT:?set OUT (the device machine sets it)}; O=/tmp/gpu-results; rm -rf "$O"
mkdir -p "$O" "$R" runs
DEV=${DEV:-cuda}; W=${W:-14}; PY=${PY:-python3}; SK=${SK:?set SK: a SemanticKITTI root}
CMP=research/experiments/gpu_compare.py
t0=$(date +%s); step() { echo "== $(( $(date +%s) - t0 ))s $*"; }
step setup
nvidia-smi -L 2>/dev/null; nproc --all; lscpu | grep "Model name"; $PY -V
if [ -z "${SKIP_INSTALL:-}" ]; then
  $PY -m pip install -q --no-index --no-deps --no-compile .whl/*.whl || exit 1
  $PY -m pip install -q --no-index --no-deps --no-build-isolation -e . || exit 1
fi
$PY -c "import torch, onnxruntime as o; print('torch', torch.__version__, torch.cuda.is_available(), 'ort', o.__version__, o.get_available_providers())"

step tests
timeout 200 $PY -m pytest -p no:cacheprovider -n 8 -rs tests/executors/test_shared_inference.py \
  tests/models/test_plugins.py tests/models/test_audit8_pointnets.py tests/models/test_train.py \
  tests/results/test_objectives.py tests/jobs/test_provenance.py tests/bench/test_bench.py \
  > "$O/tests.log" 2>&1; echo "pytest rc $?"
grep -E "passed|failed|^FAILED|^SKIPPED" "$O/tests.log" | tail -20

step grid   # the same grid on the CPU and on the device, torch both times
for k in a:cpu b:"$DEV"; do
  timeout 150 falsify grid "${CFG:-configs/paper.toml}" --backend torch --device "${k#*:}" \
    --workers "$W" --out "runs/g-${k%%:*}" --no-report --no-retrain --quiet --json \
    > "runs/g-${k%%:*}.json" || echo "grid $k failed"
done
cp runs/g-a.json "$O/grid-cpu.json"; cp runs/g-b.json "$O/grid-$DEV.json"
$PY $CMP grids runs/g-a runs/g-b | tee "$O/grid-compare.json"

step predict
for k in a:cpu b:"$DEV"; do
  for s in pixels points; do
    timeout 60 falsify predict "$SK" --backend torch --device "${k#*:}" --score $s \
      --out "runs/p-${k%%:*}-$s" --json > "$O/predict-${k%%:*}-$s.json" || echo "predict $k $s failed"
  done
done
$PY - "$O" "$DEV" <<'PY'
import json, sys
o, dev = sys.argv[1:]
for s in ("pixels", "points"):
    for k, name in (("a", "cpu"), ("b", dev)):
        x = json.load(open(f"{o}/predict-{k}-{s}.json"))
        car = x["pooled"]["car"]
        print(s, name, "pooled car iou %.6f tp %d fp %d fn %d" % (car["iou"], car["tp"], car["fp"],
                                                                   car["fn"]))
PY

step bench   # bench.toml has 450 samples
timeout 120 falsify bench pipeline --device "$DEV" --backend torch --workers "$W" \
  --samples "${BN:-450}" --json > "$O/bench-$DEV-torch.json"; echo "rc $?"

step train   # resumed against uninterrupted, and twice the same run
timeout 60 falsify dataset configs/paper.toml --scans "${SN:-64}" --seed 1 --workers "$W" \
  --out runs/syn > /dev/null || echo "dataset failed"
T="--data runs/syn --batch 16 --device $DEV --no-export --json"
for run in t3:3 t3b:3; do
  timeout 90 falsify train $T --out "runs/${run%%:*}" --epochs "${run#*:}" > /dev/null \
    2> "$O/train-${run%%:*}.log"; echo "${run%%:*} rc $?"
done
timeout 90 falsify train $T --out runs/t12 --epochs 2 > /dev/null 2> "$O/train-t12.log"
timeout 90 falsify train $T --out runs/t12 --epochs 3 --resume > /dev/null 2>> "$O/train-t12.log"
echo "resume rc $?"
$PY $CMP weights runs/t3/squeezeseg.pt runs/t12/squeezeseg.pt | tee "$O/train-resume.json"
$PY $CMP weights runs/t3/squeezeseg.pt runs/t3b/squeezeseg.pt | tee "$O/train-repeat.json"
tail -n 1 "$O"/train-*.log
step done
tar czf "$R/gpu.tar.gz" -C "$O" . && ls -la "$R"

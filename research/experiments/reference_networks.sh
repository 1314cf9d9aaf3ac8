#!/usr/bin/env bash
# The two 20-class reference networks, trained on synthetic scans of the world only:
# SqueezeSeg (90-degree front view, 64 x 512, SemanticKITTI's 19 classes) and PointNet (points).
# Run on a CUDA machine (on a CPU: DEVICE=cpu, and expect hours). Writes into ${OUT:-out}.
set -euo pipefail
OUT=${OUT:-out}
DEVICE=${DEVICE:-cuda}
WORKERS=${WORKERS:-$(nproc)}
SCANS=${SCANS:-6000}
DATA=${DATA:-/tmp/sk20-data}
mkdir -p "$OUT/squeezeseg20" "$OUT/pointnet20"
t0=$(date +%s)
# Training streets from id 1000 on, held-out validation streets from 9000: never a test config's.
falsify dataset configs/paper.toml --scans "$SCANS" --labels semantickitti --workers "$WORKERS" \
  --out "$DATA/train" --json > "$OUT/train-set.json"
falsify dataset configs/paper.toml --scans 240 --first-background 9000 --labels semantickitti \
  --workers "$WORKERS" --out "$DATA/val" --json > /dev/null
echo "data: $(( $(date +%s) - t0 )) s"
falsify train --data "$DATA/train" --val-data "$DATA/val" \
  --out "$OUT/squeezeseg20" --classes semantickitti --crf-iterations 0 --device "$DEVICE" \
  --epochs 30 --batch 32 --threads 8 --time-limit-min "${SQUEEZESEG_MIN:-7}"
echo "squeezeseg: $(( $(date +%s) - t0 )) s"
falsify train-pointnet --data "$DATA/train" --val-data "$DATA/val" \
  --out "$OUT/pointnet20" --device "$DEVICE" --epochs 60 --batch 32 --points 16384 \
  --time-limit-min "${POINTNET_MIN:-2}"
echo "pointnet: $(( $(date +%s) - t0 )) s"
rm -f "$OUT/squeezeseg20/checkpoint.pt" "$OUT/pointnet20/checkpoint.pt" \
  "$OUT/pointnet20/pointnet.onnx" \
  "$OUT/pointnet20/pointnet.json"

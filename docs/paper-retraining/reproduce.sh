#!/bin/sh
# The paper's retraining experiment from scratch, re-runnable (every step resumes or skips what
# is done): drive-style training scans, the drive-trained network, `falsify retrain` on the
# paper's space (and on a wider space), outputs copied here. Run from the repo root:
#   sh docs/paper-retraining/reproduce.sh
# DATA holds the scans and training runs (not committed), RUNS the experiment runs.
set -eu
DATA=${DATA:-../data}
RUNS=${RUNS:-runs/paper-retraining}
TRAIN_MIN=${TRAIN_MIN:-60}        # drive network: minutes of training (resumable)
FINETUNE_MIN=${FINETUNE_MIN:-20}  # fine-tuning budget per experiment
DOCS=docs/paper-retraining
mkdir -p "$RUNS"
W=models/weights

# 1. scans like a driving log: training streets 1000-1624, held-out validation streets 5000+
falsify dataset configs/paper.toml --scans 5000 --traffic drive --seed 1 \
  --first-background 1000 --backgrounds 625 --out "$DATA/drive-train" --json > /dev/null
falsify dataset configs/paper.toml --scans 120 --traffic drive --seed 2 \
  --first-background 5000 --backgrounds 50 --out "$DATA/drive-val120" --json > /dev/null

# 2. the drive-trained network: one epoch (the shipped weights are epoch 1 of a 3-epoch run,
# which is the same computation: the schedule and data order depend on the epoch only)
RESUME=""
[ -f "$DATA/train-drive/checkpoint.pt" ] && RESUME="--resume"
[ -f "$DATA/train-drive/squeezeseg.pt" ] || nice -n 5 python -m models.train \
  --data "$DATA/drive-train" --out "$DATA/train-drive" --epochs 1 \
  --val-data "$DATA/drive-val120" --time-limit-min "$TRAIN_MIN" $RESUME
python -m models.export "$DATA/train-drive/squeezeseg.pt" --out $W/squeezeseg-drive.onnx \
  --note data=falsify-dataset-drive-5000-seed1-bg1000-1624 \
  --note epochs=1 --note val_car_iou_120=0.813

# 3. the experiment: V = backgrounds 0-6, R = 7-14. At the paper's threshold on its space and
# on the space widened to 29 m (both find no blind cell for this network), then on the paper's
# space at threshold 0.69, the run that retrains.
run() {  # run NAME CONFIG [options...]: one resumable `falsify retrain`, outputs copied here
  name=$1; config=$2; shift 2
  RESUME=""
  [ -f "$RUNS/$name/stages.json" ] && RESUME="--resume"
  nice -n 5 falsify retrain "$config" --model $W/squeezeseg-drive.onnx \
    --train-data "$DATA/drive-train" --validation-backgrounds 0-6 \
    --retraining-backgrounds 7-14 --out "$RUNS/$name" --train-scans 1000 --epochs 1 \
    --time-limit-min "$FINETUNE_MIN" --workers 2 $RESUME --json "$@" > "$RUNS/$name.json"
  mkdir -p $DOCS/$name
  for f in summary.json miou_before.csv miou_after.csv comparison.html config-validation.toml; do
    if [ -f "$RUNS/$name/$f" ]; then cp "$RUNS/$name/$f" $DOCS/$name/; fi
  done
}
run paper configs/paper.toml
run paper-far configs/paper-far.toml
run paper-t069 configs/paper.toml --threshold 0.69 --oversample 5

# 4. the retrained weights of the run that retrained
python -m models.export "$RUNS/paper-t069/finetune/squeezeseg.pt" \
  --out $W/squeezeseg-drive-retrained.onnx --note base=squeezeseg-drive \
  --note experiment=docs/paper-retraining/paper-t069

#!/bin/sh
# The paper's retraining experiment with a network trained in another world: the first bundled
# SqueezeSeg (trained on the first, flat world; as bundled at 4fa6da6) on this world's
# configs/paper-far.toml, V = backgrounds 0-6, R = 7-14, threshold 0.65, with R's scans at V's
# blind cells (the paper) and, as the control, at as many random cells that are not blind.
# Re-runnable: every step skips or resumes what is done. Run from the repo root:
#   sh research/paper-retraining/reproduce-other-world.sh
set -eu
DATA=${DATA:-../data}
mkdir -p "$DATA"
FIRST=$(cd "$DATA" && pwd)/first-world
RUNS=${RUNS:-runs/paper-retraining-other-world}
DOCS=research/paper-retraining/other-world
mkdir -p "$RUNS" "$FIRST/model" "$DOCS"

# 1. the network as it was bundled (weights of 4cc0bd3, exported at 4fa6da6)
for f in squeezeseg.onnx squeezeseg.json squeezeseg.pt; do
  [ -f "$FIRST/model/$f" ] || git show 4fa6da6:models/weights/$f > "$FIRST/model/$f"
done

# 2. 1,000 scans of its own world, by the code and the command it was trained with (its
# training set's first 1,000 scans), mixed into the fine-tuning so it keeps what it knew
[ -d "$FIRST/code" ] || git worktree add --detach "$FIRST/code" 4cc0bd3
[ -f "$FIRST/train/000999.npy" ] || (cd "$FIRST/code" && PYTHONPATH=. python -m falsify.cli \
  dataset configs/paper.toml --scans 1000 --seed 1 --first-background 1000 --backgrounds 625 \
  --out "$FIRST/train" --json > /dev/null)

# 3. the runs one after the other (two torch trainings side by side on 2 cores are 5-10x
# slower); four whole epochs, no time limit, so each result is exact. A pair is the targeted run
# (the paper) and its control (as many random cells that are not blind) with one --seed, which
# sets the control's draw and the training order.
run() {  # name selection seed
  R=""; [ -f "$RUNS/$1/stages.json" ] && R="--resume"
  nice -n 5 falsify retrain configs/paper-far.toml --model "$FIRST/model/squeezeseg.onnx" \
    --train-data "$FIRST/train" --validation-backgrounds 0-6 --retraining-backgrounds 7-14 \
    --out "$RUNS/$1" --train-scans 1000 --oversample 5 --epochs 4 --workers 2 \
    --selection "$2" --seed "$3" $R --json > "$RUNS/$1.json"
  mkdir -p "$DOCS/$1"
  for f in summary.json miou_before.csv miou_after.csv config-validation.toml; do
    cp "$RUNS/$1/$f" "$DOCS/$1/"
  done
}
run blind blind 0
run control control 0
run control-seed1 control 1
run blind-seed1 blind 1
run blind-seed2 blind 2
run control-seed2 control 2
run blind-seed3 blind 3
run control-seed3 control 3
run blind-seed4 blind 4
run control-seed4 control 4
run control-seed5 control 5
run blind-seed5 blind 5
cp "$RUNS/blind/comparison.html" "$DOCS/blind/"
falsify gate "$RUNS/blind/after" --baseline "$RUNS/blind/before"

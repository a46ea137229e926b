#!/usr/bin/env bash
# Rebuild the bundled default model (models/fast-vgqcnn-default) from nothing:
# dataset -> training -> test evaluation -> pose-only baseline -> verified ONNX export
# (fp32 graphs checked against torch, plus an int8 head checked against them).
# Every step resumes: rerun the script after an interruption. On this project's 2-core CPU
# the dataset takes ~17 min and training ~2.5 h per 1M samples. Uses .venv from ./scripts/test.sh.
#
#   ./scripts/make_default_model.sh                 # everything, into data/recipe, runs/, models/
#   SAMPLES=3000000 ./scripts/make_default_model.sh # a longer schedule
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-.venv/bin/python}
SAMPLES=${SAMPLES:-900000}
DATA=data/recipe
RUN=${RUN:-runs/fast}
OUT=${OUT:-models/fast-vgqcnn-default}

$PY -m datagen recipe --version v1 --out "$DATA"
$PY -m training train --data "$DATA/crops" --arch fast_vgqcnn --out "$RUN" --resume --seed 0 \
  --samples "$SAMPLES" --optimizer adamw --base-lr 0.0002 --decay-every-samples 100000 \
  --class-balance loss_weights --val-every-samples 25000 --val-max-samples 6000 --checkpoint-every-samples 20000
$PY -m training evaluate --run "$RUN" --data "$DATA/crops"
$PY -m training baseline --data "$DATA/crops" --model mlp --out runs/baseline
$PY -m export --run "$RUN" --data "$DATA/crops" --out "$OUT" \
  --recipe "python -m datagen recipe --version v1 --out $DATA" --baseline runs/baseline/baseline_mlp.json --int8-head
cp "$RUN/eval/heatmap_test.png" "$RUN/eval/curves.png" "$OUT/"
# golden end-to-end scores of the new model on the example image (tests/test_golden_scores.py)
if [ "$OUT" = models/fast-vgqcnn-default ]; then $PY examples/golden.py --model-dir "$OUT"; fi

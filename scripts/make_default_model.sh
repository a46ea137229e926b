#!/usr/bin/env bash
# Rebuild the bundled default model (models/fast-vgqcnn-default) from nothing:
# dataset -> training -> test evaluation -> pose-only baseline -> verified ONNX export
# (fp32 graphs checked against torch, plus an int8 head checked against them).
# Every step resumes: rerun the script after an interruption. Uses .venv from ./scripts/test.sh.
#
#   ./scripts/make_default_model.sh                  # the bundled model's recipe (v2): families, sensor
#                                                    # model, physics label; four stages: the image and pose
#                                                    # streams (runs/fast-v2), the jaw-grid head fine-tuned on
#                                                    # top (runs/fast-v2-jaw), then that head again with a
#                                                    # placement stream, encoder frozen (runs/fast-v2-place),
#                                                    # then the same with every (family, label) drawn alike
#                                                    # (runs/fast-v2-family, docs/training.md); plus its
#                                                    # clean-test and leave-family-out runs
#   FAMILY_SAMPLES=600000 ./scripts/make_default_model.sh  # the v2 bundled 2026-12-07 22:30 UTC to 2026-12-08
#   FAMILY_SAMPLES=0 ./scripts/make_default_model.sh # the v2 bundled on 2026-12-07 (stages one to three)
#   PLACE_SAMPLES=0 ./scripts/make_default_model.sh # the v2 bundled 2026-12-05 to 2026-12-07: stages one and two
#   JAW_SAMPLES=0 PLACE_SAMPLES=0 ./scripts/make_default_model.sh  # the v2 bundled until 2026-12-05
#   STACKER=1 ./scripts/make_default_model.sh        # v2 plus a placement stacker on the exported network
#                                                    # (training stacker; not the bundle: docs/training.md)
#   VERSION=v1 ./scripts/make_default_model.sh       # model v1 (bundled until 2026-11-30)
#   SAMPLES=4000000 ./scripts/make_default_model.sh  # a longer first stage (a finished run resumes into it;
#                                                    # 3.6 M did not pay, docs/training.md)
#   NET_OPTS="--pose-features rotation --pose-units 64" RUN=runs/fast-v2-rot ./scripts/make_default_model.sh
#                                                    # the pose stream reads the rotation matrix: faster at
#                                                    # first, no better from 1.2 M samples on the v2 data
#                                                    # (docs/training.md); the bundled model has the paper's
#                                                    # pose stream (NET_OPTS empty)
#
# On this project's 2-core CPU: v1's dataset takes ~17 min and training ~2.5 h per 1M samples;
# v2's dataset ~40 min (1,040 objects; their physics trials replayed from datagen/recipes/v2_physics_trials.npz,
# ~3 h when simulated), training ~30-50 min per 1M samples with bf16 steps (CPUs with AVX-512 BF16 or
# AMX; ~2.5 h without): stage one SAMPLES (2.6 M), the jaw-grid stage
# JAW_SAMPLES (2.4 M; its best checkpoint, 2.28 M, was the bundle until 2026-12-07), the placement stage
# PLACE_SAMPLES (1.2 M, ~750 samples/s with the encoder frozen), the family stage FAMILY_SAMPLES (1.2 M,
# ~25 min; the bundle is its best checkpoint), the leave-family-out runs SAMPLES_LFO (3 M: 79.4% on the
# never-seen families for stage one; 71.7% at 1 M), JAW_SAMPLES, PLACE_SAMPLES and FAMILY_SAMPLES again.
set -euo pipefail
cd "$(dirname "$0")/.."
# the whole script is read before it runs (a function), so editing this file cannot break a running build
main() {
  PY=${PYTHON:-.venv/bin/python}
  VERSION=${VERSION:-v2}
  case "$VERSION" in
    v1) SAMPLES=${SAMPLES:-900000}; DATA=${DATA:-data/recipe}; RUN=${RUN:-runs/fast}; BASE=${BASE:-runs/baseline} ;;
    v2) SAMPLES=${SAMPLES:-2600000}; DATA=${DATA:-data/v2}; RUN=${RUN:-runs/fast-v2}; BASE=${BASE:-runs/baseline-v2} ;;
    *) echo "make_default_model.sh: VERSION must be v1 or v2, got $VERSION" >&2; exit 2 ;;
  esac
  OUT=${OUT:-models/fast-vgqcnn-default}
  TRAIN_OPTS=(--arch fast_vgqcnn --resume --seed 0 --optimizer adamw --base-lr 0.0002 --decay-every-samples 100000
    --class-balance loss_weights --val-every-samples 25000 --val-max-samples 6000 --checkpoint-every-samples 20000)
  read -r -a NET <<< "${NET_OPTS:-}"  # network options (training train --help), e.g. --pose-features rotation
  TRAIN_OPTS+=("${NET[@]}")
  JAW_SAMPLES=${JAW_SAMPLES:-2400000}  # the jaw-grid stage (v2): stage one's best checkpoint, the new head
  [ "$VERSION" = v2 ] || JAW_SAMPLES=0  # starting at zero, a quarter of the learning rate; 0: no jaw stage
  # the placement stage (v2, after the jaw stage): the jaw stage's exported model, its encoder frozen, its
  # head fine-tuned reading each grasp's placement row (vgq.placement) beside its pose; 0: no placement stage
  PLACE_SAMPLES=${PLACE_SAMPLES:-1200000}
  [ "$JAW_SAMPLES" != 0 ] || PLACE_SAMPLES=0
  # the family stage (v2, after the placement stage): its best checkpoint fine-tuned on, each epoch drawn so
  # that every (object family, label) cell weighs alike (training --sampling family; 0: no family stage)
  FAMILY_SAMPLES=${FAMILY_SAMPLES:-1200000}
  # STACKER=1 (v2): a placement stacker on the exported network's scores (training stacker, docs/training.md),
  # fitted on the recipe's stacker objects and judged on its 16-new-objects test; the network is exported to
  # RUN-jaw/model, the stacked model written to OUT
  STACKER=${STACKER:-0}
  [ "$VERSION" = v2 ] || STACKER=0
  EXPORTED=$OUT
  EXPORT_OPTS=(--int8-head)
  EVAL_OPTS=()
  if [ "$VERSION" = v2 ]; then
    EVAL_OPTS+=(--max-n 50000)  # of 425,616 test crops (all take ~23 min per copy on 2 cores); the clean copy: the same rows
    TRAIN_OPTS+=(--precision auto)  # bf16 steps where the CPU has bf16 (~1.9x)
    EXPORT_OPTS+=(--int8-encoder)  # kept only if it passes its accuracy check; the service times both at start-up
  fi

  $PY -m datagen recipe --version "$VERSION" --out "$DATA" --no-leave-out  # the leave-family-out split comes later
  # train_stages DATA RUN SAMPLES: stage one into RUN, then (JAW_SAMPLES > 0) the jaw-grid stage into RUN-jaw,
  # then (PLACE_SAMPLES > 0) the placement stage into RUN-place, starting from RUN-jaw exported to RUN-jaw/model
  train_stages() {
    $PY -m training train --data "$1" --out "$2" --samples "$3" "${TRAIN_OPTS[@]}"
    if [ "$JAW_SAMPLES" != 0 ]; then
      $PY -m training train --data "$1" --out "$2-jaw" --samples "$JAW_SAMPLES" "${TRAIN_OPTS[@]}" \
        --init "$2" --roi-head jaw --base-lr 0.00005
    fi
    if [ "$PLACE_SAMPLES" != 0 ]; then
      [ -f "$2-jaw/model/model_card.json" ] || $PY -m export --run "$2-jaw" --data "$1" --out "$2-jaw/model" --no-calibration
      $PY -m training train --data "$1" --out "$2-place" --samples "$PLACE_SAMPLES" "${TRAIN_OPTS[@]}" \
        --init "$2-jaw/model" --roi-head jaw --freeze-encoder --base-lr 0.0001 --val-every-samples 50000 \
        --placement image --placement-units 64 --placement-lr-scale 30 --placement-dropout 0.1
    fi
    if [ "$PLACE_SAMPLES" != 0 ] && [ "$FAMILY_SAMPLES" != 0 ]; then  # the same head, every (family, label) drawn alike
      $PY -m training train --data "$1" --out "$2-family" --samples "$FAMILY_SAMPLES" "${TRAIN_OPTS[@]}" \
        --init "$2-place/checkpoints/best.pt" --roi-head jaw --freeze-encoder --base-lr 0.0001 --val-every-samples 50000 \
        --placement image --placement-units 64 --placement-lr-scale 30 --placement-dropout 0.1 \
        --sampling family --class-balance none
    fi
  }
  final() {
    if [ "$PLACE_SAMPLES" != 0 ] && [ "$FAMILY_SAMPLES" != 0 ]; then echo "$1-family"
    elif [ "$PLACE_SAMPLES" != 0 ]; then echo "$1-place"; elif [ "$JAW_SAMPLES" != 0 ]; then echo "$1-jaw"; else echo "$1"; fi
  }
  FINAL=$(final "$RUN")
  [ "$STACKER" = 0 ] || EXPORTED="$FINAL/model"
  train_stages "$DATA/crops" "$RUN" "$SAMPLES"
  $PY -m training evaluate --run "$FINAL" --data "$DATA/crops" "${EVAL_OPTS[@]}"
  if [ -d "$DATA/crops_clean_test" ]; then  # the same test grasps without the sensor model
    $PY -m training evaluate --run "$FINAL" --data "$DATA/crops_clean_test" --name test_clean "${EVAL_OPTS[@]}"
  fi
  $PY -m training baseline --data "$DATA/crops" --model mlp --out "$BASE"
  export_model() {
    $PY -m export --run "$FINAL" --data "$DATA/crops" --out "$EXPORTED" "$@" \
      --recipe "python -m datagen recipe --version $VERSION --out $DATA" --baseline "$BASE/baseline_mlp.json" \
      "${EXPORT_OPTS[@]}"
  }
  export_model
  MORE=()
  [ "$STACKER" = 0 ] || MORE=(--more-test 16 --stacker)  # the stacker's fit objects and its judge (new objects)
  # the rest of the recipe: the leave-family-out split (and the stacker's data)
  $PY -m datagen recipe --version "$VERSION" --out "$DATA" "${MORE[@]}"
  if [ -d "$DATA/crops_lfo" ]; then  # leave-family-out: the same stages, never seeing the held-out families
    train_stages "$DATA/crops_lfo" "$RUN-lfo" "${SAMPLES_LFO:-3000000}"
    LFO=$(final "$RUN-lfo")
    $PY -m training evaluate --run "$LFO" --data "$DATA/crops_lfo" "${EVAL_OPTS[@]}"
    $PY -m export.leave_family_out --model-dir "$EXPORTED" "$LFO/eval/metrics_test.json"  # into the card, no re-export
  fi
  if [ "$STACKER" = 1 ]; then  # ~15 min: fit (800 rows per object), judge, the card's test results re-measured
    if ! { [ "$OUT/model_card.json" -nt "$EXPORTED/model_card.json" ] && grep -q '"stacker"' "$OUT/model_card.json"; }; then
      $PY -m training stacker --model-dir "$EXPORTED" --fit "$DATA/crops_stacker" --judge "$DATA/crops_more" \
        --out "$OUT" --per-object 800 --test "$DATA/crops" --test-clean "$DATA/crops_clean_test" --test-max-n 50000
      $PY -m export.evaluate --model-dir "$OUT" --data "$DATA/crops_more" --split test --max-n 200000 \
        --card-key test_more_objects  # per family on 16 new objects each (the stacker's judge set)
    fi
  fi
  cp "$FINAL/eval/heatmap_test.png" "$FINAL/eval/curves.png" "$OUT/"
  if [ "$VERSION" = v2 ]; then  # planned grasps' p_hold (the score mapped to how often planner candidates
    # hold) and their order (a ranker on the score, the jaw width and the gripper's pose against the table)
    # (~35 min: 150 scenes of objects outside the dataset (docs/planning.md, top view), 32 candidates each, 8 pybullet trials; docs/planning.md)
    [ -f "$FINAL/pool_train.json" ] || $PY -m planning.bench pool --model "$OUT" --heldout unseen \
      --scenes 150 --per-scene 32 --trials 8 --threads 1 --json "$FINAL/pool_train.json"
    $PY -m planning.calibration "$FINAL/pool_train.json" --model "$OUT"
    $PY -m planning.ranker "$FINAL/pool_train.json" --model "$OUT"  # the planner's order (score, width, table pose)
  fi
  if [ "$OUT" = models/fast-vgqcnn-default ]; then
    # the held-out examples the tests score the bundled model on: test-split crops and whole images
    # of its own test objects, then the golden end-to-end scores (tests/test_golden_scores.py)
    $PY examples/make_heldout.py --data "$DATA/crops"
    $PY examples/make_heldout_images.py --grasps "$DATA/grasps"
    $PY examples/golden.py --model-dir "$OUT"
  fi
}
main "$@"
exit

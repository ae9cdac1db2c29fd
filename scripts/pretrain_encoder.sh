#!/usr/bin/env bash
# The camera encoder the `tiny` recipe starts from, made the way it was made: a pretraining set of
# its own (simgen seed 1001, never a benchmark or demo split), `clfbev pretrain` on its dense
# labels, and the encoder written to clfbev/weights/encoder_tiny.pt with its record beside it
# (clfbev/weights/encoder_tiny.json: the commands, the pretraining set's identity, the images
# seen, the wall time and the final losses).
#   bash scripts/pretrain_encoder.sh              # the shipped encoder (about 40 min on 2 cores)
#   OUT=out/pre_small SCENES=10 EPOCHS=2 WEIGHTS=out/pre_small/encoder.pt bash scripts/pretrain_encoder.sh
# Everything resumes: rerun the same command after an interruption (even kill -9). The same
# settings on the same code give the same data bytes and, with the same thread count, the same
# weights (clfbev/weights/encoder_tiny.json records both, and the code version).
set -euo pipefail
cd "$(dirname "$0")/.."

SCENES=${SCENES:-60}            # urban scenes, all in the pretraining split
SAMPLES=${SAMPLES:-10}          # key frames per scene: 6 images each
RES=${RES:-704x396}             # the benchmark's camera resolution (the loader resizes to the config's)
SEED=${SEED:-1001}              # the pretraining set's own seed
EPOCHS=${EPOCHS:-8}
THREADS=${THREADS:-$(nproc)}
OUT=${OUT:-out/pretrain}        # data and run folder
WEIGHTS=${WEIGHTS:-clfbev/weights/encoder_tiny.pt}
DATA=$OUT/data
RUN=$OUT/run

bash scripts/install.sh
export PYOPENGL_PLATFORM=${PYOPENGL_PLATFORM:-egl}
mkdir -p "$OUT"

make=(.venv/bin/simgen make --scenes "$SCENES" --samples-per-scene "$SAMPLES" --resolution "$RES" --seed "$SEED"
      --val-fraction 0 --dense-labels --out "$DATA" --quiet)
echo "pretrain_encoder: data $DATA ($SCENES scenes x $SAMPLES key frames at $RES, seed $SEED, dense labels)"
t0=$(date +%s)
"${make[@]}"
make_s=$(( $(date +%s) - t0 ))

pretrain=(.venv/bin/clfbev pretrain --data "$DATA" --config tiny --out "$RUN" --epochs "$EPOCHS" --threads "$THREADS")
resume=()
[ -f "$RUN/last.pt" ] && resume=(--resume)
echo "pretrain_encoder: pretrain $RUN ($EPOCHS epochs, $THREADS threads)"
t0=$(date +%s)
"${pretrain[@]}" "${resume[@]}"
pretrain_s=$(( $(date +%s) - t0 ))

mkdir -p "$(dirname "$WEIGHTS")"
cp "$RUN/encoder.pt" "$WEIGHTS.tmp" && mv "$WEIGHTS.tmp" "$WEIGHTS"
.venv/bin/python scripts/encoder_record.py "$WEIGHTS" --run "$RUN" --make-command "${make[*]}" \
  --make-seconds "$make_s" --pretrain-seconds "$pretrain_s" --threads "$THREADS"
echo "pretrain_encoder: wrote $WEIGHTS and ${WEIGHTS%.pt}.json"

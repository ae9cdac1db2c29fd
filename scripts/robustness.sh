#!/usr/bin/env bash
# The robustness suite in one command: paired degraded sets, the five variants, load-time
# corruptions, and the report (robustness_out/robustness.{json,md,png}).
#   bash scripts/robustness.sh            # 12 scenes x 20 samples, 8 epochs per variant (hours on 2 cores)
#   bash scripts/robustness.sh --quick    # 6 scenes x 10 samples, 3 epochs, 3 load-time corruptions (about 28 min on 2 cores, docs/robustness.md)
# Every stage resumes or reuses: a set that exists is not regenerated, a variant whose
# OUT/runs/VARIANT/best.pt exists is not retrained (point RUNS at other runs to reuse them).
set -euo pipefail
cd "$(dirname "$0")/.."
QUICK=0
[ "${1:-}" = "--quick" ] && QUICK=1
bash scripts/install.sh
export PYOPENGL_PLATFORM=${PYOPENGL_PLATFORM:-egl}
# beam_missing:N drops N of the 32 rings: 16 leaves half of the beams, 24 leaves 8.
if [ $QUICK = 1 ]; then SCENES=${SCENES:-6}; SAMPLES=${SAMPLES:-10}; EPOCHS=${EPOCHS:-3}
  CORRUPT=(--corrupt beam_missing:16 --corrupt lidar_missing --corrupt camera_crash:6)
else
  SCENES=${SCENES:-12}; SAMPLES=${SAMPLES:-20}; EPOCHS=${EPOCHS:-8}
  CORRUPT=(--corrupt beam_missing:16 --corrupt beam_missing:24 --corrupt lidar_missing --corrupt camera_crash:6
           --corrupt camera_crash:1 --corrupt fov:120)
fi
RES=${RES:-704x396}
OUT=${OUT:-robustness_out}
SETS=${SETS:-$OUT/sets}
RUNS=${RUNS:-$OUT/runs}
MODALITY_DROPOUT=${MODALITY_DROPOUT:-0.25}
mkdir -p "$OUT" "$SETS" "$RUNS"
t0=$(date +%s)

# 1. Paired sets: one world (same preset, seed and scenes), different sensors.
make_set() {  # name, flags...
  local name=$1; shift
  .venv/bin/simgen make --preset urban --scenes "$SCENES" --samples-per-scene "$SAMPLES" --resolution "$RES" \
    --seed 0 --out "$SETS/$name" --quiet "$@"
}
make_set clean
make_set fog1 --fog 1
make_set fog3 --fog 3
make_set fog5 --fog 5
make_set occlusion_heavy --occlusion heavy
make_set lens3 --lens-occlusion 3
t1=$(date +%s)

# 2. The five variants (the demo's recipe); full also with modality dropout.
train() {  # variant, run name, extra flags...
  local variant=$1 name=$2; shift 2
  local resume=()
  if [ -f "$RUNS/$name/last.pt" ]; then resume=(--resume)     # continue (a no-op when finished)
  elif [ -f "$RUNS/$name/best.pt" ]; then return; fi           # a checkpoint given to reuse
  .venv/bin/clfbev train --data "$SETS/clean" --config tiny --variant "$variant" --out "$RUNS/$name" \
    --epochs "$EPOCHS" --seed 0 --threads "$(nproc)" --quiet "${resume[@]}" "$@"
}
for v in lidar camera concat mcm full; do train "$v" "$v"; done
train full full_md --modality-dropout "$MODALITY_DROPOUT"
t2=$(date +%s)

# 3. Every checkpoint on every condition through the official DetectionEval.
ckpts=()
for name in lidar camera concat mcm full full_md; do ckpts+=(--ckpt "$name=$RUNS/$name/best.pt"); done
.venv/bin/clfbev robustness "${ckpts[@]}" \
  --set "clean=$SETS/clean" --set "fog1=$SETS/fog1" --set "fog3=$SETS/fog3" --set "fog5=$SETS/fog5" \
  --set "occlusion_heavy=$SETS/occlusion_heavy" --set "lens3=$SETS/lens3" \
  "${CORRUPT[@]}" --out "$OUT"
t3=$(date +%s)
echo "{\"sets_s\": $((t1 - t0)), \"train_s\": $((t2 - t1)), \"evaluate_s\": $((t3 - t2)), \"total_s\": $((t3 - t0))}" \
  > "$OUT/timing.json"
echo "robustness: wrote $OUT/robustness.md ($((t3 - t0)) s)"

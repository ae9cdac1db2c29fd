#!/usr/bin/env bash
# The main job, end to end on a fresh machine: install, generate a small urban dataset, train the
# tiny CL-FusionBEV, evaluate it with the official nuScenes metrics, and write demo_out/REPORT.md
# with the metrics, the loss curve and camera / BEV / attention pictures.
#   bash scripts/demo.sh                       # defaults below (about 30 min on 2 idle CPU cores)
#   SCENES=4 SAMPLES=6 CAMERA_STEPS=40 LIDAR_STEPS=20 FUSION_STEPS=10 bash scripts/demo.sh   # a quick look
#   RECIPE=scratch bash scripts/demo.sh        # `full` trained from scratch instead
# RECIPE=staged (the default) runs scripts/staged.sh at the demo's budget (the camera on its frozen
# encoder's cached features CAMERA_STEPS, the lidar LIDAR_STEPS, the fusion FUSION_STEPS from both)
# and evaluates its experts file (the fused model, with the camera and lidar stages for a lost
# sensor). RECIPE=scratch trains `full` from scratch with the tiny config's recipe (`clfbev train
# --config tiny`, see clfbev/run/train_config.py: recipe; EPOCHS only shortens it). Both recipes'
# measured times and figures: the README.
# Every stage resumes: rerunning after an interruption continues where it stopped.
set -euo pipefail
cd "$(dirname "$0")/.."
RECIPE=${RECIPE:-staged}
CAMERA_STEPS=${CAMERA_STEPS:-1440}   # RECIPE=staged's stages
LIDAR_STEPS=${LIDAR_STEPS:-720}
FUSION_STEPS=${FUSION_STEPS:-360}
case $RECIPE in
  scratch | staged) ;;
  *) echo "demo: RECIPE must be scratch or staged, got '$RECIPE'" >&2; exit 2 ;;
esac
bash scripts/install.sh
export PYOPENGL_PLATFORM=${PYOPENGL_PLATFORM:-egl}
SCENES=${SCENES:-12}
SAMPLES=${SAMPLES:-20}
RES=${RES:-704x396}
OUT=demo_out
DATA=$OUT/data
RUN=$OUT/run
mkdir -p "$OUT"
t0=$(date +%s)

.venv/bin/simgen make --scenes "$SCENES" --samples-per-scene "$SAMPLES" --resolution "$RES" --out "$DATA" --seed 0
.venv/bin/simgen check "$DATA" | tee "$OUT/check.txt"
t1=$(date +%s)

# No validation while training: the evaluation below scores the final weights on sim-val, and
# choosing a checkpoint on that same split would flatter them (and cost a minute an epoch).
case $RECIPE in
  scratch)
    resume=()
    [ -f "$RUN/last.pt" ] && resume=(--resume)
    epochs=()
    [ -n "${EPOCHS:-}" ] && epochs=(--epochs "$EPOCHS")
    .venv/bin/clfbev train --data "$DATA" --config tiny --variant full --out "$RUN" --seed 0 --val-split '' \
      --threads "$(nproc)" "${epochs[@]}" "${resume[@]}"
    CKPT=$RUN/last.pt ;;
  staged)
    DATA=$DATA OUT=$OUT/staged PY=.venv/bin/python THREADS=$(nproc) CAMERA_STEPS=$CAMERA_STEPS LIDAR_STEPS=$LIDAR_STEPS \
      FUSION_STEPS=$FUSION_STEPS bash scripts/staged.sh
    RUN=$OUT/staged/fusion
    CKPT=$OUT/staged/experts.pt ;;
esac
t2=$(date +%s)

.venv/bin/clfbev eval --data "$DATA" --ckpt "$CKPT" --split sim-val --out "$OUT/eval"
t3=$(date +%s)
# The fifth sim-val sample, or the last of the first val scene when scenes are shorter.
show_sample=$(( SAMPLES > 4 ? 4 : SAMPLES - 1 ))
.venv/bin/clfbev show --data "$DATA" --results "$OUT/eval/results.json" --sample "$show_sample" --out "$OUT/overlay.png" \
  --attention --ckpt "$RUN/last.pt"
t4=$(date +%s)

cat > "$OUT/timing.json" <<EOF
{"scenes": $SCENES, "generate_s": $((t1 - t0)), "train_s": $((t2 - t1)), "eval_s": $((t3 - t2)), "show_s": $((t4 - t3)), "total_s": $((t4 - t0))}
EOF
.venv/bin/python scripts/demo_report.py "$OUT" --run "$RUN" --timing "$OUT/timing.json"
echo "demo: wrote $OUT/REPORT.md ($((t4 - t0)) s)"

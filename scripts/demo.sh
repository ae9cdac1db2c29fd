#!/usr/bin/env bash
# The main job, end to end on a fresh machine: install, generate a small urban dataset, train the
# tiny CL-FusionBEV from scratch, evaluate it with the official nuScenes metrics, and write
# demo_out/REPORT.md with the metrics, the loss curve and camera / BEV / attention pictures.
#   bash scripts/demo.sh                       # defaults below (about 30 min on 2 CPU cores)
#   SCENES=4 SAMPLES=6 EPOCHS=1 bash scripts/demo.sh   # a quick look
# Training uses the tiny config's recipe (`clfbev train --config tiny`, see clfbev/run/train_config.py:
# recipe); EPOCHS only shortens it.
# Every stage resumes: rerunning after an interruption continues where it stopped.
set -euo pipefail
cd "$(dirname "$0")/.."
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

resume=()
[ -f "$RUN/last.pt" ] && resume=(--resume)
epochs=()
[ -n "${EPOCHS:-}" ] && epochs=(--epochs "$EPOCHS")
# No validation while training: the evaluation below scores the final weights on sim-val, and
# choosing a checkpoint on that same split would flatter them (and cost a minute an epoch).
.venv/bin/clfbev train --data "$DATA" --config tiny --variant full --out "$RUN" --seed 0 --val-split '' \
  --threads "$(nproc)" "${epochs[@]}" "${resume[@]}"
t2=$(date +%s)

.venv/bin/clfbev eval --data "$DATA" --ckpt "$RUN/last.pt" --split sim-val --out "$OUT/eval"
t3=$(date +%s)
# The fifth sim-val sample, or the last of the first val scene when scenes are shorter.
show_sample=$(( SAMPLES > 4 ? 4 : SAMPLES - 1 ))
.venv/bin/clfbev show --data "$DATA" --results "$OUT/eval/results.json" --sample "$show_sample" --out "$OUT/overlay.png" \
  --attention --ckpt "$RUN/last.pt"
t4=$(date +%s)

cat > "$OUT/timing.json" <<EOF
{"scenes": $SCENES, "generate_s": $((t1 - t0)), "train_s": $((t2 - t1)), "eval_s": $((t3 - t2)), "show_s": $((t4 - t3)), "total_s": $((t4 - t0))}
EOF
.venv/bin/python scripts/demo_report.py "$OUT" --timing "$OUT/timing.json"
echo "demo: wrote $OUT/REPORT.md ($((t4 - t0)) s)"

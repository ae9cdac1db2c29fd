#!/usr/bin/env bash
# The staged recipe in one command, BEVFusion's practice at CPU scale: the camera and the lidar
# detectors trained apart, each in its own stage, then a short fusion stage that starts from both;
# the fused model and the two single-sensor models together are OUT/experts.pt, which answers a
# sample without a lidar or without cameras with the model of the sensor it has.
#   DATA=data/sim bash scripts/staged.sh                 # the whole recipe into OUT
#   DATA=data/sim bash scripts/staged.sh --list          # each stage's state and CPU time; runs nothing
#   DATA=data/sim bash scripts/staged.sh cache camera    # only these stages (a stage's inputs must be done)
# The stages, each a folder of OUT:
#   cache   clfbev cache-features: the frozen image encoder's features of the training split, once
#   camera  clfbev train --variant camera --image-freeze --feature-cache OUT/cache       CAMERA_STEPS
#   lidar   clfbev train --variant lidar                                                  LIDAR_STEPS
#   fusion  clfbev train --variant FUSION_VARIANT --lidar-init OUT/lidar/last.pt --camera-init
#           OUT/camera/last.pt --image-freeze --feature-cache OUT/cache, modality dropout
#           DROP_LIDAR / DROP_CAMERA (off by default)                                      FUSION_STEPS
# and, once the fusion stage is done, OUT/experts.pt: the fused model with the camera and lidar
# stages' models as its experts for a lost sensor (clfbev experts; evaluate it with --ckpt).
# Everything resumes: rerun the same command after an interruption, kill -9 of its process group
# included (kill -9 -PGID; a stage's training left running alone keeps OUT locked until it ends).
# A done stage is skipped, an interrupted one continues from its last.pt (--resume; the cache
# keeps its entries). Each stage's settings are recorded in OUT/staged.json when it starts, and a
# rerun that gives a started stage other settings is refused (exit 2), never mixed into it.
# OUT/staged.json also holds each stage's CPU time (user + system of its processes, part by part)
# and the recipe's total in CPU-hours (scripts/staged_record.py).
# A script rather than a `clfbev train` option: each stage is a plain clfbev command, printed and
# runnable alone, and the training loop stays one run's.
set -euo pipefail
cd "$(dirname "$0")/.."

# The knobs. The step budgets, sized by the measured step costs of docs/benchmarks.md (one thread,
# beside other work; the recipe's own costs land in OUT/staged.json):
# - LIDAR_STEPS 1200: the benchmark's budget (scripts/benchmark.sh), so the lidar stage is the
#   benchmark's `lidar` run; a step 1.25-1.35 s, about 0.4-0.5 CPU-hours.
# - CAMERA_STEPS 3600: the lidar stage's CPU again. A camera step on cached features with the
#   encoder frozen costs 0.36-0.39 s, under a third of a lidar step, so the camera gets three
#   times the steps (11 epochs of the benchmark's 640 training samples), where at the benchmark's
#   1200 fine-tuned steps alone it finds 2-3% of the cars' AP.
# - FUSION_STEPS 600: the short stage, "Fusion in two stages"' 600 steps from the lidar run,
#   after which the fused model and its lidar control were level; a fused step reads the same
#   cached features and costs 2.05-2.48 s (about 0.35-0.4 CPU-hours for the stage).
# - DROP_LIDAR 0, DROP_CAMERA 0: modality dropout off. With 0.25 and 0.3333 (a quarter of the
#   samples without lidar, a quarter without cameras) the fused model alone keeps 0.109 NDS
#   without its lidar, but loses 3.1 clean points and 3.1 with 24 beams missing; the experts
#   answer a lost sensor with its stage's model instead (docs/benchmarks.md, "Per-sensor experts").
DATA=${DATA:-}                          # nuScenes-format dataroot (simgen make), required
OUT=${OUT:-staged_out}                  # the stages' folders and staged.json
OUT=${OUT%/}
CONFIG=${CONFIG:-tiny}                  # model config: tiny, paper or a YAML file
SEED=${SEED:-0}
SPLIT=${SPLIT:-sim-train}               # the training split of every stage (the cache holds its images)
IMAGE_INIT=${IMAGE_INIT:-shipped}       # the frozen image encoder: shipped, or an encoder checkpoint
CAMERA_STEPS=${CAMERA_STEPS:-3600}
LIDAR_STEPS=${LIDAR_STEPS:-1200}
FUSION_STEPS=${FUSION_STEPS:-600}
FUSION_VARIANT=${FUSION_VARIANT:-full}  # concat, mcm or full
DROP_LIDAR=${DROP_LIDAR:-0}
DROP_CAMERA=${DROP_CAMERA:-0}
TRAIN_ARGS=${TRAIN_ARGS:-}              # more `clfbev train` options for every training stage
THREADS=${THREADS:-$(nproc)}            # torch threads per training (not part of the settings)

STAGES=(cache camera lidar fusion)
LIST=0
if [ "${1:-}" = "--list" ]; then LIST=1; shift; fi
for s in "$@"; do
  case " ${STAGES[*]} " in
    *" $s "*) ;;
    *) echo "staged: unknown stage '$s' (allowed: ${STAGES[*]})" >&2; exit 2 ;;
  esac
done
[ $# -gt 0 ] && SELECTED=("$@") || SELECTED=("${STAGES[@]}")
case " concat mcm full " in
  *" $FUSION_VARIANT "*) ;;
  *) echo "staged: FUSION_VARIANT '$FUSION_VARIANT' is not a fused variant (allowed: concat, mcm, full)" >&2; exit 2 ;;
esac
if [ -z "$DATA" ] || [ ! -d "$DATA" ]; then
  echo "staged: DATA '$DATA' is not a dataroot folder (DATA=DIR: a nuScenes-format dataroot, e.g. of simgen make)" >&2
  exit 2
fi

# PY: the Python that runs clfbev; by default the project's .venv, installed (or checked) first.
if [ -z "${PY:-}" ]; then
  bash scripts/install.sh
  PY=.venv/bin/python
fi
rec() { "$PY" scripts/staged_record.py "$@"; }

# Each stage's command: stage_args STAGE sets argv to its clfbev arguments, the dataroot left out.
# Its settings are those words and the dataroot's identity (scripts/data_identity.py), so that a
# remade dataset is not mixed into a started stage; --threads is not one of them.
data_id=$("$PY" scripts/data_identity.py "$DATA")
read -ra more <<< "$TRAIN_ARGS"
train=(--config "$CONFIG" --seed "$SEED" --split "$SPLIT" --val-split '' "${more[@]}")
frozen=(--image-init "$IMAGE_INIT" --image-freeze --feature-cache "$OUT/cache")
stage_args() {
  case $1 in
    cache) argv=(cache-features --config "$CONFIG" --image-init "$IMAGE_INIT" --split "$SPLIT" --out "$OUT/cache") ;;
    camera) argv=(train "${train[@]}" --variant camera "${frozen[@]}" --max-steps "$CAMERA_STEPS"
                  --out "$OUT/camera") ;;
    lidar) argv=(train "${train[@]}" --variant lidar --max-steps "$LIDAR_STEPS" --out "$OUT/lidar") ;;
    fusion) argv=(train "${train[@]}" --variant "$FUSION_VARIANT" --lidar-init "$OUT/lidar/last.pt"
                  --camera-init "$OUT/camera/last.pt" "${frozen[@]}" --modality-dropout-lidar "$DROP_LIDAR"
                  --modality-dropout-camera "$DROP_CAMERA" --max-steps "$FUSION_STEPS" --out "$OUT/fusion") ;;
  esac
}
declare -A NEEDS=([cache]="" [camera]="cache" [lidar]="" [fusion]="cache camera lidar")
settings() { stage_args "$1"; echo "data:$data_id ${argv[*]}"; }

# Every stage's settings are checked before anything runs (a refusal costs nothing): OUT holds one recipe.
for s in "${STAGES[@]}"; do rec state "$OUT" "$s" "$(settings "$s")" >/dev/null; done
if [ $LIST = 1 ]; then
  for s in "${SELECTED[@]}"; do echo "$s $(rec state "$OUT" "$s" "$(settings "$s")")"; done
  [ -f "$OUT/staged.json" ] && rec report "$OUT"
  exit 0
fi

mkdir -p "$OUT"
# One recipe per OUT at a time: the lock is inherited by the stages' processes, so it is held
# until the last of them has ended, even one whose script was killed.
exec 9>"$OUT/.lock"
if ! flock -n 9; then
  echo "staged: $OUT is in use by another run of the recipe (or a stage of one still running)" >&2
  exit 2
fi

for s in "${SELECTED[@]}"; do
  state=$(rec state "$OUT" "$s" "$(settings "$s")")
  if [ "$state" = done ]; then
    echo "staged: $s done earlier (skipped)"
    continue
  fi
  for need in ${NEEDS[$s]}; do
    if [ "$(rec state "$OUT" "$need" "$(settings "$need")")" != done ]; then
      echo "staged: the $s stage needs the $need stage done first (bash scripts/staged.sh $need)" >&2
      exit 2
    fi
  done
  stage_args "$s"
  extra=()
  if [ "${argv[0]}" = train ]; then
    extra=(--threads "$THREADS")
    if [ -f "$OUT/$s/last.pt" ]; then
      extra+=(--resume)
      echo "staged: $s resumes from $OUT/$s/last.pt"
    else
      echo "staged: $s starts"
    fi
  else
    echo "staged: $s $([ "$state" = started ] && echo "continues (entries kept)" || echo starts)"
  fi
  rc=0
  rec run "$OUT" "$s" "$(settings "$s")" -- "$PY" -m clfbev "${argv[0]}" --data "$DATA" "${argv[@]:1}" "${extra[@]}" ||
    rc=$?
  if [ $rc -ne 0 ]; then
    echo "staged: $s stopped (exit $rc); rerun the same command to resume" >&2
    exit $rc
  fi
done
# The fused model with the camera and lidar stages' models as its per-sensor experts (clfbev
# experts): evaluated, a sample without any lidar point is answered by the camera stage's model,
# one without any camera by the lidar stage's. Seconds; made again from the stages' weights.
if [ "$(rec state "$OUT" fusion "$(settings fusion)")" = done ]; then
  "$PY" -m clfbev experts --fused "$OUT/fusion/last.pt" --camera "$OUT/camera/last.pt" --lidar "$OUT/lidar/last.pt" \
    --out "$OUT/experts.pt"
fi
rec report "$OUT"

#!/usr/bin/env bash
# The robustness suite in one command: the benchmark's models on a held-out world in every
# condition, beside each condition's sensor-visibility oracle, and the report
# (OUT/robustness.{json,md,png}).
#   bash scripts/robustness.sh            # 8 held-out scenes x 10 key frames; 15 paired sets (the clean one among them), 10 corruptions
#   bash scripts/robustness.sh --quick    # 3 scenes x 5 key frames; clean, fog 3, snowfall 2.5, night, 3 corruptions
#   JOBS=2 bash scripts/robustness.sh     # the models split over 2 processes of one thread each
# The models are scripts/benchmark.sh's runs lidar_s0, camera_s0, concat_s0, mcm_s0, full_s0,
# fullmd_s0 (full trained with modality dropout), and full_s0 with its camera and lidar stages as
# per-sensor experts (clfbev experts): each from BENCH's run folder where it was evaluated there,
# else from its record's weights (docs/results/RUN/weights.pt.xz). A model that is neither is
# left out with a line saying so; with none, nothing runs.
# The world is one the models never saw: urban seed 2 (the benchmark's is seed 1, the demo's 0),
# every scene in sim-val. Every set pairs with the clean one (same world, other sensors).
# Everything resumes: a set made is not made again, an evaluated cell (model x condition) is
# reused while its checkpoint and set are unchanged (clfbev robustness). Each set and each
# evaluation is recorded with its CPU time in OUT/staged.json (scripts/staged_record.py), so the
# suite's cost is known however many times it was interrupted and continued.
set -euo pipefail
cd "$(dirname "$0")/.."
QUICK=0
[ "${1:-}" = "--quick" ] && QUICK=1
if [ $QUICK = 1 ]; then
  SCENES=${SCENES:-3}; SAMPLES=${SAMPLES:-5}
  SETS_ARGS=("clean:" "fog3:--fog 3" "snow2.5:--snow 2.5" "night:--night")
  CORRUPT=(lidar_missing beam_missing:24 camera_crash:6)
else
  SCENES=${SCENES:-8}; SAMPLES=${SAMPLES:-10}
  SETS_ARGS=("clean:" "fog1:--fog 1" "fog2:--fog 2" "fog3:--fog 3" "fog4:--fog 4" "fog5:--fog 5"
             "rain10:--rain 10" "rain25:--rain 25" "rain50:--rain 50" "snow0.5:--snow 0.5" "snow1:--snow 1"
             "snow2.5:--snow 2.5" "night:--night" "occlusion_heavy:--occlusion heavy" "lens3:--lens-occlusion 3")
  # MultiCorrupt's and the fusion robustness benchmarks' failures: fewer beams (16 and 24 of 32
  # rings gone), points reduced (level 2: 40 %), the lidar or every camera or one camera lost,
  # the lidar's field of view at +-60 deg, a spatial misalignment (level 2: 2 deg and 4 cm on each
  # axis), a temporal one (the lidar 2 sweeps, 0.1 s, behind) and motion blur (level 2: 21 px).
  CORRUPT=(beam_missing:16 beam_missing:24 density:0.4 lidar_missing camera_crash:6 camera_crash:1 fov:120
           misalign:LIDAR_TOP:2 late:LIDAR_TOP:2 motion_blur:21)
fi
RES=${RES:-704x396}
SEED=${SEED:-2}
SUFFIX=""; [ $QUICK = 0 ] || SUFFIX=_quick
OUT=${OUT:-robustness_out$SUFFIX}
SETS=${SETS:-$OUT/sets}
BENCH=${BENCH:-benchmark_out}
RECORD=${RECORD:-docs/results}
MODELS=(lidar_s0 camera_s0 concat_s0 mcm_s0 full_s0 fullmd_s0)
bash scripts/install.sh
rec() { .venv/bin/python scripts/staged_record.py "$@"; }
export PYOPENGL_PLATFORM=${PYOPENGL_PLATFORM:-egl}

# 1. The models: an evaluated benchmark run's last.pt, else its record's weights.
weights_of() {  # run -> the file to evaluate, or nothing
  if [ -f "$BENCH/$1/eval/metrics_summary.json" ] && [ -f "$BENCH/$1/last.pt" ]; then echo "$BENCH/$1/last.pt"
  elif [ -f "$RECORD/$1/weights.pt.xz" ]; then echo "$RECORD/$1/weights.pt.xz"; fi
}
ckpts=()
for run in "${MODELS[@]}"; do
  w=$(weights_of "$run")
  if [ -n "$w" ]; then ckpts+=(--ckpt "$run=$w"); else echo "robustness: $run left out (not in $BENCH, no $RECORD/$run/weights.pt.xz)"; fi
done
fused=$(weights_of full_s0)
cam=$( [ -f "$BENCH/camstage_s0/last.pt" ] && echo "$BENCH/camstage_s0/last.pt" || echo "$RECORD/camstage_s0/weights.pt.xz")
lid=$( [ -f "$BENCH/lidarstage_s0/last.pt" ] && echo "$BENCH/lidarstage_s0/last.pt" || echo "$RECORD/lidarstage_s0/weights.pt.xz")
experts=0
if [ -n "$fused" ] && [ -f "$cam" ] && [ -f "$lid" ]; then
  experts=1
else
  echo "robustness: experts_s0 left out (full_s0 and its stages' weights are not all there)"
fi
if [ ${#ckpts[@]} -eq 0 ] && [ $experts = 0 ]; then
  echo "robustness: no model to test: run scripts/benchmark.sh first (or restore its records in $RECORD)" >&2
  exit 2
fi
mkdir -p "$OUT" "$SETS"
if [ $experts = 1 ]; then
  .venv/bin/clfbev experts --fused "$fused" --camera "$cam" --lidar "$lid" --out "$OUT/experts_s0.pt"
  ckpts+=(--ckpt "experts_s0=$OUT/experts_s0.pt")
fi
t0=$(date +%s)

# 2. The paired sets of the held-out world (simgen make resumes a set cut short).
sets=()
for spec in "${SETS_ARGS[@]}"; do
  name=${spec%%:*}
  read -ra flags <<< "${spec#*:}"
  echo "robustness: set $name"
  make=(.venv/bin/simgen make --preset urban --scenes "$SCENES" --samples-per-scene "$SAMPLES" --resolution "$RES"
        --seed "$SEED" --val-fraction 1 --out "$SETS/$name" --quiet "${flags[@]}")
  [ "$(rec state "$OUT" "set_$name" "${make[*]:1}")" = done ] || rec run "$OUT" "set_$name" "${make[*]:1}" -- "${make[@]}"
  sets+=(--set "$name=$SETS/$name")
done
t1=$(date +%s)

# 3. Every model and the oracle on every condition through the official DetectionEval.
corrupt=()
for c in "${CORRUPT[@]}"; do corrupt+=(--corrupt "$c"); done
evaluate() {  # STAGE CKPT_ARGS... : one clfbev robustness process, recorded as STAGE
  local stage=$1; shift
  rec run "$OUT" "$stage" "clfbev robustness" -- .venv/bin/clfbev robustness "$@" "${sets[@]}" "${corrupt[@]}" --out "$OUT"
}
JOBS=${JOBS:-1}
if [ "$JOBS" -gt 1 ]; then
  # Cells are independent, so the models are dealt round-robin to JOBS one-thread processes. The
  # first computes the oracle's cells before its models; the others start once those are all
  # there, so that no oracle cell is computed twice.
  groups=()     # per job, the indices of its models' NAME=CKPT in ckpts
  for ((i = 1; i < ${#ckpts[@]}; i += 2)); do
    groups[(i / 2) % JOBS]+="$i "
  done
  # A cell is done when its cell.json is there (clfbev robustness writes it last), in the folder
  # clfbev.run.robustness._cell_dir names (':' as '_'). Were the names to drift, the wait would
  # only last until job 1 ends: slower, never wrong.
  oracle_cells=()
  for spec in "${SETS_ARGS[@]}"; do oracle_cells+=("$OUT/oracle/${spec%%:*}/cell.json"); done
  for c in "${CORRUPT[@]}"; do oracle_cells+=("$OUT/oracle/${c//:/_}/cell.json"); done
  oracle_done() { local f; for f in "${oracle_cells[@]}"; do [ -f "$f" ] || return 1; done; }
  pids=()
  for ((j = 0; j < ${#groups[@]}; j++)); do
    args=()
    for i in ${groups[j]}; do args+=(--ckpt "${ckpts[i]}"); done
    OMP_NUM_THREADS=1 evaluate "evaluate_job$((j + 1))" "${args[@]}" > "$OUT/job$((j + 1)).log" 2>&1 &
    pids+=($!)
    echo "robustness: job $((j + 1)) ($OUT/job$((j + 1)).log): ${args[*]}"
    while [ $j = 0 ] && kill -0 "${pids[0]}" 2> /dev/null && ! oracle_done; do sleep 5; done
  done
  for ((j = 0; j < ${#pids[@]}; j++)); do
    wait "${pids[j]}" || { echo "robustness: job $((j + 1)) failed; see $OUT/job$((j + 1)).log" >&2; exit 1; }
  done
fi
# The whole report: with JOBS, every cell is there already and is only read.
evaluate evaluate "${ckpts[@]}"
t2=$(date +%s)
echo "{\"sets_s\": $((t1 - t0)), \"evaluate_s\": $((t2 - t1)), \"total_s\": $((t2 - t0))}" > "$OUT/.timing.json.tmp"
mv "$OUT/.timing.json.tmp" "$OUT/timing.json"
rec report "$OUT"
echo "robustness: wrote $OUT/robustness.md ($((t2 - t0)) s)"

#!/usr/bin/env bash
# The benchmark in one command: one fixed dataset, every variant trained by the recipe that suits
# it at about equal CPU-hours, evaluated on sim-val with the official metric, and docs/results.md
# written from the run folders.
#   bash scripts/benchmark.sh                  # every run; lidar and full with 2 seeds
#   bash scripts/benchmark.sh lidar full       # only these variants (all their seeds)
#   bash scripts/benchmark.sh full_s1          # or only these runs (VARIANT_sSEED)
#   bash scripts/benchmark.sh --list [VARIANT...]   # the runs and their state; runs nothing
#   SCENES=3 SAMPLES=3 RES=352x198 LIDAR_STEPS=4 CAMERA_STEPS=4 FUSION_STEPS=4 LIDAR_ALONE_STEPS=8 \
#     CAMERA_ALONE_STEPS=8 OUT=benchmark_out/smoke RESULTS=benchmark_out/smoke/results.md \
#     bash scripts/benchmark.sh lidar full     # a smoke test of the whole chain
#
# The runs (docs/benchmarks.md measured why):
#   lidar_sS    `clfbev train --variant lidar`, LIDAR_ALONE_STEPS
#   camera_s0   `clfbev train --variant camera` on the frozen shipped encoder's cached features,
#               CAMERA_ALONE_STEPS
#   full_sS, mcm_s0, concat_s0   the staged recipe (scripts/staged.sh): a camera stage (cached
#               features, CAMERA_STEPS) and a lidar stage (LIDAR_STEPS) of seed S, shared by the
#               fused variants of that seed, then each variant's fusion stage from both (FUSION_STEPS)
#   fullmd_s0   full's fusion stage with modality dropout (a quarter of the samples without lidar,
#               a quarter without cameras), the fused model the robustness suite also tests
# A fused run's CPU-hours are those of all its stages (the cache and the shared stages included);
# the step budgets give lidar, camera and full about the same (the table reports what each took).
#
# Everything resumes: rerun the same command after an interruption (even kill -9). Each stage is
# a plain clfbev command, recorded with its CPU time in OUT/staged.json (scripts/staged_record.py):
# a done stage is skipped, a started one continues from its last.pt, a stage asked for with other
# settings (other code included) is refused. The table is rewritten after every evaluation.
# Each evaluated run leaves its record in RECORD (tracked: run.json, metrics_summary.json,
# cpu.json, its identities and its weights, weights.pt.xz: the state dict alone, xz-compressed,
# which `clfbev eval --ckpt` reads; a fused run's camera and lidar stages keep theirs in
# RECORD/camstage_sS and RECORD/lidarstage_sS, for its per-sensor experts). On another machine or a fresh clone a recorded run is
# restored from there instead of retrained, but only onto the same settings, the same data (its
# layout's hash, data_id) and the same code (code_id: the git trees of clfbev/ and simgen/).
# Delete a run's record folder to run it again.
set -euo pipefail
cd "$(dirname "$0")/.."

# The knobs. The defaults are the benchmark: change them only for a smoke test, into another OUT.
# Step costs measured on the 2-core machine, one thread each (docs/benchmarks.md): a lidar step
# 1.25-1.35 CPU-s, a camera step on cached features 0.36 CPU-s, a fused step on them 2.05-2.48.
# The staged full recipe: 3600 camera + 1200 lidar + 600 fused steps, about 1.3 CPU-hours with
# the cache; lidar alone gets 3600 steps and camera alone 12000 for about the same.
SCENES=${SCENES:-40}            # urban scenes; the last 20% are sim-val (40 -> 32 train, 8 val)
SAMPLES=${SAMPLES:-20}          # key frames per scene
RES=${RES:-704x396}             # camera resolution WxH
CAMERA_STEPS=${CAMERA_STEPS:-3600}             # the staged recipe's camera stage
LIDAR_STEPS=${LIDAR_STEPS:-1200}               # ... its lidar stage
FUSION_STEPS=${FUSION_STEPS:-600}              # ... its fusion stage
LIDAR_ALONE_STEPS=${LIDAR_ALONE_STEPS:-3600}   # lidar_sS
CAMERA_ALONE_STEPS=${CAMERA_ALONE_STEPS:-12000} # camera_s0
DROP_LIDAR=0.25                 # fullmd_s0's modality dropout (the share of samples without lidar)
DROP_CAMERA=0.3333              # ... and of the others without cameras: a quarter of all
OUT=${OUT:-benchmark_out}       # data and run folders
OUT=${OUT%/}
RESULTS=${RESULTS:-docs/results.md}
RECORD=${RECORD:-${RESULTS%.md}}  # the evaluated runs' records, a folder per run (docs/results/)
THREADS=${THREADS:-$(nproc)}    # torch threads per stage; 1 to run two benchmarks side by side
DATA_SEED=1
VAL_FRACTION=0.2
DATA=$OUT/data

# The runs, in the order that makes a partial table most useful: the lidar baseline and the full
# model first, then the ablations, then the second seeds (which only measure the spread).
ALL_RUNS=(lidar_s0 full_s0 concat_s0 mcm_s0 camera_s0 fullmd_s0 lidar_s1 full_s1)
VARIANTS=(lidar camera concat mcm full)     # clfbev.config.VARIANTS (checked by the tests)

LIST=0
if [ "${1:-}" = "--list" ]; then LIST=1; shift; fi
# Names are checked before anything is installed or created, so a typo costs nothing.
for v in "$@"; do
  case " ${VARIANTS[*]} ${ALL_RUNS[*]} " in
    *" $v "*) ;;
    *) echo "benchmark: unknown variant or run '$v' (allowed: ${VARIANTS[*]}, or a run: ${ALL_RUNS[*]})" >&2; exit 2 ;;
  esac
done
variant_of() { case ${1%_s*} in fullmd) echo full ;; *) echo "${1%_s*}" ;; esac; }
RUNS=()
for run in "${ALL_RUNS[@]}"; do
  if [ $# -eq 0 ] || [[ " $* " == *" $(variant_of "$run") "* ]] || [[ " $* " == *" $run "* ]]; then RUNS+=("$run"); fi
done

# The benchmark's settings: a record or an OUT of other settings is never mixed into this table.
settings="{\"scenes\": $SCENES, \"samples_per_scene\": $SAMPLES, \"resolution\": \"$RES\", \"data_seed\": $DATA_SEED, \
\"val_fraction\": $VAL_FRACTION, \"camera_steps\": $CAMERA_STEPS, \"lidar_steps\": $LIDAR_STEPS, \
\"fusion_steps\": $FUSION_STEPS, \"lidar_alone_steps\": $LIDAR_ALONE_STEPS, \"camera_alone_steps\": $CAMERA_ALONE_STEPS}"

# The code's identity: the git trees of the two packages, and with uncommitted changes in them
# "-dirty-" and a hash of those changes; "unknown" outside a git checkout (never restored).
code_id() {
  local trees changes
  trees=$(git rev-parse HEAD:clfbev HEAD:simgen 2>/dev/null) || { echo unknown; return; }
  changes=$(git diff HEAD -- clfbev simgen; git ls-files -o --exclude-standard -- clfbev simgen |
            while read -r f; do echo "$f $(git hash-object "$f")"; done)
  echo "$(echo "$trees" | sha1sum | cut -c1-12)$( [ -z "$changes" ] || echo "-dirty-$(echo "$changes" | sha1sum | cut -c1-8)")"
}
CODE_ID=$(code_id)
# The data's identity (scripts/data_identity.py), once OUT's data has been made: a record of other
# data is never restored. Before that (`--list` on a fresh clone) the settings and code decide.
data_id=$(cat "$OUT/data_id" 2>/dev/null || true)
recorded() {  # run -> true when RECORD holds its evaluation, of this benchmark's settings, data and code
  [ -f "$RECORD/$1/metrics_summary.json" ] && [ "$(cat "$RECORD/$1/benchmark.json" 2>/dev/null)" = "$settings" ] &&
    [ "$(cat "$RECORD/$1/code_id" 2>/dev/null)" = "$CODE_ID" ] && [ "$CODE_ID" != unknown ] &&
    { [ -z "$data_id" ] || [ "$(cat "$RECORD/$1/data_id" 2>/dev/null)" = "$data_id" ]; }
}
state_of() {  # run -> done | recorded | started | pending (from the files alone: no python yet)
  if [ -f "$OUT/$1/eval/metrics_summary.json" ]; then echo done
  elif [ -f "$OUT/$1/last.pt" ]; then echo started
  elif recorded "$1"; then echo recorded
  else echo pending; fi
}
if [ $LIST = 1 ]; then
  for run in "${RUNS[@]}"; do echo "$run $(state_of "$run")"; done
  exit 0
fi

bash scripts/install.sh
export PYOPENGL_PLATFORM=${PYOPENGL_PLATFORM:-egl}
PY=.venv/bin/python
mkdir -p "$OUT"
rec() { "$PY" scripts/staged_record.py "$@"; }

# One OUT holds one benchmark: runs of other data or other step budgets must not be mixed into
# one table.
if [ -f "$OUT/benchmark.json" ] && [ "$(cat "$OUT/benchmark.json")" != "$settings" ]; then
  echo "benchmark: $OUT holds a benchmark with other settings ($(cat "$OUT/benchmark.json")); use another OUT" >&2
  exit 2
fi
echo "$settings" > "$OUT/benchmark.json"

# 1. The dataset. simgen make resumes by itself and only re-merges the tables when complete.
echo "benchmark: data $DATA ($SCENES scenes x $SAMPLES key frames at $RES, seed $DATA_SEED)"
.venv/bin/simgen make --scenes "$SCENES" --samples-per-scene "$SAMPLES" --resolution "$RES" --seed "$DATA_SEED" \
  --val-fraction "$VAL_FRACTION" --out "$DATA" --quiet
data_id=$($PY scripts/data_identity.py "$DATA")
echo "$data_id" > "$OUT/.data_id.tmp" && mv "$OUT/.data_id.tmp" "$OUT/data_id"
[ -f "$OUT/scored.json" ] || $PY scripts/scored_boxes.py "$DATA" --out "$OUT/scored.json"   # what each AP rests on

# 2. The stages. stage_args STAGE sets argv to its clfbev command (the dataroot and the threads
# left out); needs_of STAGE lists the stages it starts from. Settings = the command and the data.
train=(train --config tiny --split sim-train --val-split '')
frozen=(--image-init shipped --image-freeze --feature-cache "$OUT/cache")
stage_args() {
  local name=$1 seed=${1##*_s}
  case ${1%_s*} in
    cache) argv=(cache-features --config tiny --image-init shipped --split sim-train --out "$OUT/cache") ;;
    camstage) argv=("${train[@]}" --seed "$seed" --variant camera "${frozen[@]}" --max-steps "$CAMERA_STEPS") ;;
    lidarstage) argv=("${train[@]}" --seed "$seed" --variant lidar --max-steps "$LIDAR_STEPS") ;;
    lidar) argv=("${train[@]}" --seed "$seed" --variant lidar --max-steps "$LIDAR_ALONE_STEPS") ;;
    camera) argv=("${train[@]}" --seed "$seed" --variant camera "${frozen[@]}" --max-steps "$CAMERA_ALONE_STEPS") ;;
    full | mcm | concat | fullmd)
      argv=("${train[@]}" --seed "$seed" --variant "$(variant_of "$name")" --lidar-init "$OUT/lidarstage_s$seed/last.pt"
            --camera-init "$OUT/camstage_s$seed/last.pt" "${frozen[@]}" --max-steps "$FUSION_STEPS")
      [ "${1%_s*}" = fullmd ] && argv+=(--modality-dropout-lidar "$DROP_LIDAR" --modality-dropout-camera "$DROP_CAMERA") ;;
  esac
  [ "$name" = cache ] || argv+=(--out "$OUT/$name")
}
needs_of() {
  local seed=${1##*_s}
  case ${1%_s*} in
    camera) echo cache ;;
    camstage) echo cache ;;
    full | mcm | concat | fullmd) echo "cache camstage_s$seed lidarstage_s$seed" ;;
  esac
}
# The code is part of every stage's settings: a change to clfbev/ or simgen/ restarts the runs
# (a started stage of other code is refused, never continued on this one).
stage_settings() { stage_args "$1"; echo "code:$CODE_ID data:$data_id ${argv[*]}"; }

run_stage() {  # stage: run (or finish) it unless done
  local stage=$1 state extra=()
  state=$(rec state "$OUT" "$stage" "$(stage_settings "$stage")")
  [ "$state" = done ] && return 0
  stage_args "$stage"
  if [ "${argv[0]}" = train ]; then
    extra=(--threads "$THREADS")
    [ -f "$OUT/$stage/last.pt" ] && extra+=(--resume)
  fi
  echo "benchmark: $stage $([ "$state" = started ] && echo continues || echo starts)"
  rc=0
  rec run "$OUT" "$stage" "$(stage_settings "$stage")" -- "$PY" -m clfbev "${argv[0]}" --data "$DATA" "${argv[@]:1}" \
    "${extra[@]}" || rc=$?
  if [ $rc -ne 0 ]; then
    echo "benchmark: $stage stopped (exit $rc); rerun the same command to resume" >&2
    exit $rc
  fi
}

table() {
  $PY scripts/results_table.py "$OUT" --runs "${ALL_RUNS[@]}" --out "$RESULTS"
}
keep_record() {  # run: its small files and its weights into RECORD/run, each replaced whole
  local rec=$RECORD/$1 f
  mkdir -p "$rec"
  for f in "$OUT/benchmark.json" "$OUT/data_id" "$OUT/$1/code_id" "$OUT/$1/cpu.json" \
           "$OUT/$1/eval/metrics_summary.json" "$OUT/$1/weights.pt.xz"; do
    cp "$f" "$rec/.$(basename "$f").tmp" && mv "$rec/.$(basename "$f").tmp" "$rec/$(basename "$f")"
  done
  # run.json's argv[0] is the file the interpreter ran, a path of this machine: the record names
  # the program instead (written atomically by clfbev.io).
  "$PY" -c 'import json, sys; from clfbev import io; r = json.loads(open(sys.argv[1]).read()); r["argv"][0] = "clfbev"
io.write_json(sys.argv[2], r)' "$OUT/$1/run.json" "$rec/run.json"
}
keep_stage_weights() {  # run: the weights of a fused run's camera and lidar stages (its per-sensor
  # experts, clfbev experts) into RECORD/STAGE, once per seed
  local stage
  for stage in $(needs_of "$1"); do
    if [ "$stage" = cache ] || [ -f "$RECORD/$stage/weights.pt.xz" ] || [ ! -f "$OUT/$stage/last.pt" ]; then continue; fi
    "$PY" -m clfbev export --ckpt "$OUT/$stage/last.pt" --out "$OUT/$stage/weights.pt.xz"
    mkdir -p "$RECORD/$stage"
    cp "$OUT/$stage/weights.pt.xz" "$RECORD/$stage/.weights.pt.xz.tmp"
    mv "$RECORD/$stage/.weights.pt.xz.tmp" "$RECORD/$stage/weights.pt.xz"
  done
}
restore() {  # run: its record back into OUT/run, as its evaluation left it
  mkdir -p "$OUT/$1/eval"
  cp "$RECORD/$1/run.json" "$RECORD/$1/cpu.json" "$RECORD/$1/code_id" "$RECORD/$1/weights.pt.xz" "$OUT/$1/"
  cp "$RECORD/$1/metrics_summary.json" "$OUT/$1/eval/"
}

# 3. Each run: its stages, its evaluation (recorded as a stage too), its CPU, its record.
evaluated=0
for run in "${RUNS[@]}"; do
  case $(state_of "$run") in
    done) keep_record "$run"; keep_stage_weights "$run"; echo "benchmark: $run evaluated earlier (skipped)"; continue ;;
    recorded) restore "$run"; echo "benchmark: $run restored from $RECORD/$run (delete that folder to rerun it)"
              continue ;;
  esac
  stages=($(needs_of "$run") "$run")
  for stage in "${stages[@]}"; do run_stage "$stage"; done
  echo "benchmark: eval $run"
  rc=0
  rec run "$OUT" "eval_$run" "code:$CODE_ID data:$data_id eval $OUT/$run/last.pt" -- "$PY" -m clfbev eval --data "$DATA" \
    --ckpt "$OUT/$run/last.pt" --split sim-val --out "$OUT/$run/eval" || rc=$?
  [ $rc -eq 0 ] || { echo "benchmark: eval $run stopped (exit $rc); rerun to resume" >&2; exit $rc; }
  "$PY" -m clfbev export --ckpt "$OUT/$run/last.pt" --out "$OUT/$run/weights.pt.xz"
  "$PY" scripts/staged_record.py cpu "$OUT" "${stages[@]}" "eval_$run" > "$OUT/$run/.cpu.json.tmp"
  mv "$OUT/$run/.cpu.json.tmp" "$OUT/$run/cpu.json"
  echo "$CODE_ID" > "$OUT/$run/code_id"
  keep_record "$run"
  keep_stage_weights "$run"
  table
  evaluated=1
done

# 4. With nothing evaluated now (all done or restored), the table is still rewritten: the code
# that writes it may have changed since.
[ $evaluated = 1 ] || table

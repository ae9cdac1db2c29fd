#!/usr/bin/env bash
# The benchmark in one command: one fixed dataset, every variant trained with the same recipe and
# step budget, evaluated on sim-val with the official metric, and docs/results.md written from
# the run folders.
#   bash scripts/benchmark.sh                  # all five variants; lidar and full with 2 seeds
#   bash scripts/benchmark.sh lidar full       # only these variants (all their seeds)
#   bash scripts/benchmark.sh full_s1          # or only these runs (VARIANT_sSEED)
#   bash scripts/benchmark.sh --list [VARIANT...]   # the runs and their state; runs nothing
#   SCENES=3 SAMPLES=3 STEPS=4 RES=352x198 OUT=benchmark_out/smoke RESULTS=benchmark_out/smoke/results.md \
#     bash scripts/benchmark.sh lidar full     # a smoke test of the whole chain
# Everything resumes: rerun the same command after an interruption (even kill -9). A run with an
# evaluation is skipped, a trained run is only evaluated, a partial training continues from its
# last.pt. The table is rewritten after every run, so it can be completed in parts.
# Each evaluated run also leaves its record (run.json, wall.jsonl, metrics_summary.json; a few kB)
# in RECORD, which is tracked: on another machine or a fresh clone a recorded run is restored
# from there instead of retrained, so the table can be completed in parts across machines too,
# but only for the same settings and the same data (its layout's hash, in data_id).
# Delete a run's record folder to run it again.
set -euo pipefail
cd "$(dirname "$0")/.."

# The knobs. The defaults are the benchmark: change them only for a smoke test, into another OUT.
# STEPS is the one step budget shared by every variant, sized for the slowest one, full, on the
# 2-core development machine. Measured with the tiny recipe (10 sweeps, GT-paste on) at 704x396:
# 1.7-2.0 s per step of 2 samples with both threads and nothing else running (full_s0), so 1200
# steps are 34-40 min, plus about 1 min to start (the GT-paste database reads the training
# split's lidar once) and 2-4 min to evaluate 160 samples: about 45 min. Other load on the cores
# stretches all of this; the table reports the wall time each run took.
SCENES=${SCENES:-40}            # urban scenes; the last 20% are sim-val (40 -> 32 train, 8 val)
SAMPLES=${SAMPLES:-20}          # key frames per scene
RES=${RES:-704x396}             # camera resolution WxH
STEPS=${STEPS:-1200}            # optimizer steps per run
OUT=${OUT:-benchmark_out}       # data and run folders
RESULTS=${RESULTS:-docs/results.md}
RECORD=${RECORD:-${RESULTS%.md}}  # the evaluated runs' records, a folder per run (docs/results/)
THREADS=${THREADS:-$(nproc)}    # torch threads per training; 1 to run two benchmarks side by side
DATA_SEED=1
VAL_FRACTION=0.2
DATA=$OUT/data

# The runs, in the order that makes a partial table most useful: the lidar baseline and the full
# model first, then the ablations, then the second seeds (which only measure the spread).
ALL_RUNS=(lidar_s0 full_s0 concat_s0 mcm_s0 camera_s0 lidar_s1 full_s1)
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
RUNS=()
for run in "${ALL_RUNS[@]}"; do
  if [ $# -eq 0 ] || [[ " $* " == *" ${run%_s*} "* ]] || [[ " $* " == *" $run "* ]]; then RUNS+=("$run"); fi
done

# The benchmark's settings: a record or an OUT of other settings is never mixed into this table.
settings="{\"scenes\": $SCENES, \"samples_per_scene\": $SAMPLES, \"resolution\": \"$RES\", \"data_seed\": $DATA_SEED, \"val_fraction\": $VAL_FRACTION, \"steps\": $STEPS}"

# The data's identity (scripts/data_identity.py), once OUT's data has been made: a record of other
# data is never restored. Before that (`--list` on a fresh clone) the settings alone decide.
data_id=$(cat "$OUT/data_id" 2>/dev/null || true)
recorded() {  # run -> true when RECORD holds its evaluation, of this benchmark's settings and data
  [ -f "$RECORD/$1/metrics_summary.json" ] && [ "$(cat "$RECORD/$1/benchmark.json" 2>/dev/null)" = "$settings" ] &&
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

# One OUT holds one benchmark: runs of other data or another step budget must not be mixed
# into one table, and a resumed training would refuse another --max-steps anyway.
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

ckpt_step() {  # the optimizer step a last.pt was written at
  $PY -c 'import sys; from clfbev.run.checkpoint import load_checkpoint; print(load_checkpoint(sys.argv[1])["step"])' "$1"
}
record() {  # run folder, stage, extra JSON fields: one line per part in RUN/wall.jsonl
  echo "{\"stage\": \"$2\", $3, \"threads\": $THREADS, \"cores\": $(nproc), \"end\": \"$(date -u +%Y-%m-%dT%H:%M:%SZ)\"}" >> "$1/wall.jsonl"
}
table() {
  $PY scripts/results_table.py "$OUT" --runs "${ALL_RUNS[@]}" --out "$RESULTS"
}
keep_record() {  # run: its small files into RECORD/run, each replaced whole
  local rec=$RECORD/$1 f
  mkdir -p "$rec"
  for f in "$OUT/benchmark.json" "$OUT/data_id" "$OUT/$1/run.json" "$OUT/$1/wall.jsonl" "$OUT/$1/eval/metrics_summary.json"; do
    cp "$f" "$rec/.$(basename "$f").tmp" && mv "$rec/.$(basename "$f").tmp" "$rec/$(basename "$f")"
  done
}
restore() {  # run: its record back into OUT/run, as its evaluation left it
  mkdir -p "$OUT/$1/eval"
  cp "$RECORD/$1/run.json" "$RECORD/$1/wall.jsonl" "$OUT/$1/"
  cp "$RECORD/$1/metrics_summary.json" "$OUT/$1/eval/"
}

# 2. Train and evaluate each run; the table is rewritten after each evaluation.
evaluated=0
for run in "${RUNS[@]}"; do
  dir=$OUT/$run
  variant=${run%_s*}
  seed=${run##*_s}
  case $(state_of "$run") in
    done) keep_record "$run"; echo "benchmark: $run evaluated earlier (skipped)"; continue ;;
    recorded) restore "$run"; echo "benchmark: $run restored from $RECORD/$run (delete that folder to rerun it)"
              continue ;;
  esac
  mkdir -p "$dir"

  step=0
  [ -f "$dir/last.pt" ] && step=$(ckpt_step "$dir/last.pt")
  if [ "$step" -lt "$STEPS" ]; then
    resume=()
    if [ -f "$dir/last.pt" ]; then
      resume=(--resume)
      echo "benchmark: train $run (resumes at step $step of $STEPS)"
    else
      echo "benchmark: train $run ($STEPS steps)"
    fi
    # Only what is not the recipe: the recipe is `--config tiny`'s defaults, the same for all.
    # No validation while training (--val-split ''): nothing is selected on the evaluation split,
    # and the evaluated checkpoint is last.pt, the weights after the last step.
    t0=$(date +%s); rc=0
    .venv/bin/clfbev train --data "$DATA" --config tiny --variant "$variant" --seed "$seed" --out "$dir" \
      --max-steps "$STEPS" --val-split '' --threads "$THREADS" "${resume[@]}" || rc=$?
    # The part's time counts even when it was interrupted: the table reports the wall time spent.
    to=$step
    [ -f "$dir/last.pt" ] && to=$(ckpt_step "$dir/last.pt")
    record "$dir" train "\"from_step\": $step, \"to_step\": $to, \"seconds\": $(( $(date +%s) - t0 )), \"exit\": $rc"
    if [ $rc -ne 0 ]; then
      echo "benchmark: train $run stopped (exit $rc); rerun the same command to resume" >&2
      exit $rc
    fi
  else
    echo "benchmark: $run trained earlier ($step steps)"
  fi

  echo "benchmark: eval $run"
  t0=$(date +%s)
  .venv/bin/clfbev eval --data "$DATA" --ckpt "$dir/last.pt" --split sim-val --out "$dir/eval"
  record "$dir" eval "\"seconds\": $(( $(date +%s) - t0 ))"
  keep_record "$run"
  table
  evaluated=1
done

# 3. With nothing evaluated now (all done or restored), the table is still rewritten: the code
# that writes it may have changed since.
[ $evaluated = 1 ] || table

"""The record of a staged recipe (scripts/staged.sh): OUT/staged.json, each stage's settings,
whether it is done, and the CPU time of every part of it.

    python scripts/staged_record.py state OUT STAGE SETTINGS           # prints pending | started | done
    python scripts/staged_record.py run OUT STAGE SETTINGS -- CMD ...  # runs CMD as a part of STAGE
    python scripts/staged_record.py report OUT                         # CPU hours per stage and in all
    python scripts/staged_record.py cpu OUT STAGE...                   # those stages' CPU seconds, as JSON

SETTINGS is one string: the stage's command line without the options that do not change its
result (threads, progress, --resume), and the data's identity. A stage keeps the settings it
started with; ``state`` and ``run`` refuse others (one line naming the stage and the first
differing option, exit 2), so a rerun never mixes two recipes in one OUT.

A part is one process of a stage: the first start, or a continuation after an interruption.
Its CPU time is the user + system time of the process and of the children it waited for
(``getrusage(RUSAGE_CHILDREN)`` around it). While it runs the part is rewritten every
:data:`INTERIM_S` seconds with the process's times so far (``/proc/PID/stat``), so a part killed
with SIGKILL, which cannot record its end, keeps its CPU time up to that last rewrite
(``"ended": false``). ``run`` exits with the command's exit code (128 + N for a signal N); a
stage is done when a part of it exits 0.

staged.json (written atomically, :mod:`clfbev.io`): ``{"format", "stages": {STAGE: {"settings",
"done", "cpu_s", "parts": [{"started", "wall_s", "user_s", "sys_s", "exit", "ended"}]}}, "cpu_s",
"cpu_hours"}``; times in seconds, ``started`` in UTC.
"""
from __future__ import annotations

import fcntl
import json
import os
import resource
import signal
import subprocess
import sys
import time
from contextlib import contextmanager
from datetime import datetime, timezone
from pathlib import Path

from clfbev import io

FORMAT = "clfbev-staged-v1"
RECORD = "staged.json"
INTERIM_S = 20.0


class Refused(Exception):
    """Bad input: one line for stderr, exit code 2."""


def load(out: Path) -> dict:
    """OUT's record (an empty one where there is none yet)."""
    path = out / RECORD
    if not path.exists():
        return {"format": FORMAT, "stages": {}}
    try:
        record = json.loads(path.read_text())
    except (OSError, ValueError) as e:
        raise Refused(f"{path} is unreadable ({e}); it is the staged recipe's record") from None
    if not isinstance(record, dict) or record.get("format") != FORMAT or not isinstance(record.get("stages"), dict):
        raise Refused(f"{path} is not a {FORMAT} record")
    return record


def save(out: Path, record: dict) -> None:
    """Write the record with its totals, atomically."""
    for stage in record["stages"].values():
        stage["cpu_s"] = round(sum(p["user_s"] + p["sys_s"] for p in stage["parts"]), 3)
    record["cpu_s"] = round(sum(s["cpu_s"] for s in record["stages"].values()), 3)
    record["cpu_hours"] = round(record["cpu_s"] / 3600.0, 4)
    io.write_json(out / RECORD, record, indent=1)


def _options(settings: str) -> dict[str, str]:
    """{option: its values} of a settings string ('--max-steps 1200 --seed 0' -> {'--max-steps': '1200', ...});
    words before the first option under ''."""
    opts, key = {}, ""
    for word in settings.split():
        if word.startswith("--"):
            key = word
            opts.setdefault(key, "")
        else:
            opts[key] = f"{opts.get(key, '')} {word}".strip()
    return opts


def check_settings(record: dict, stage: str, settings: str, out: Path) -> None:
    """Refuse ``settings`` for a stage that started with others, naming the first difference."""
    before = record["stages"].get(stage, {}).get("settings")
    if before is None or before == settings:
        return
    old, new = _options(before), _options(settings)
    key = next((k for k in [*old, *new] if old.get(k) != new.get(k)), "")
    what = f"{key or 'the command'} {old.get(key, '(none)')!s} -> {new.get(key, '(none)')!s}"
    raise Refused(f"the {stage} stage in {out} was started with other settings ({what}); keep its settings, "
                  f"or use another OUT, or delete {out / stage} and its entry in {out / RECORD}")


def state(out: Path, stage: str, settings: str) -> str:
    """'done', 'started' (a part ran, none exited 0) or 'pending'; refuses other settings."""
    record = load(out)
    check_settings(record, stage, settings, out)
    entry = record["stages"].get(stage)
    if entry is None:
        return "pending"
    return "done" if entry["done"] else "started"


def _proc_cpu(pid: int) -> tuple[float, float]:
    """(user, system) seconds of process ``pid`` and its waited-for children so far, from
    /proc/PID/stat (fields 14-17, utime stime cutime cstime, in clock ticks); (0, 0) where unreadable."""
    try:
        text = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return 0.0, 0.0
    fields = text[text.rindex(")") + 2:].split()     # field 3 (state) onwards: the name may hold spaces
    tick = os.sysconf("SC_CLK_TCK")
    utime, stime, cutime, cstime = (int(v) for v in fields[11:15])
    return (utime + cutime) / tick, (stime + cstime) / tick


@contextmanager
def locked(out: Path):
    """An exclusive lock for a read-modify-write of OUT's record: processes that record other
    stages of one OUT at the same time (two benchmark runs side by side) never undo each other's
    writes. Its own file: staged.sh holds OUT/.lock for a whole recipe."""
    out.mkdir(parents=True, exist_ok=True)
    with open(out / ".record.lock", "a") as f:
        fcntl.flock(f, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)


def put(out: Path, stage: str, entry: dict) -> None:
    """Write ``stage``'s entry into OUT's record as it is now on disk."""
    with locked(out):
        record = load(out)
        record["stages"][stage] = entry
        save(out, record)


def run(out: Path, stage: str, settings: str, command: list[str]) -> int:
    """Run ``command`` as a new part of ``stage``, recording it; returns its exit code."""
    with locked(out):
        record = load(out)
        check_settings(record, stage, settings, out)
        entry = record["stages"].setdefault(stage, {"settings": settings, "done": False, "parts": []})
        part = {"started": datetime.now(timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"), "wall_s": 0.0, "user_s": 0.0,
                "sys_s": 0.0, "exit": None, "ended": False}
        entry["parts"].append(part)
        save(out, record)
    # Ctrl-C reaches the command too (one process group); the record waits for its end. A Python
    # handler, unlike SIG_IGN, is not inherited by the command.
    handler = signal.signal(signal.SIGINT, lambda *_: None)
    try:
        before, t0 = resource.getrusage(resource.RUSAGE_CHILDREN), time.monotonic()
        proc = subprocess.Popen(command)
        while True:
            try:
                proc.wait(timeout=INTERIM_S)
                break
            except subprocess.TimeoutExpired:
                part["user_s"], part["sys_s"] = (round(v, 3) for v in _proc_cpu(proc.pid))
                part["wall_s"] = round(time.monotonic() - t0, 3)
                put(out, stage, entry)
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
    finally:
        signal.signal(signal.SIGINT, handler)
    part.update(wall_s=round(time.monotonic() - t0, 3), user_s=round(after.ru_utime - before.ru_utime, 3),
                sys_s=round(after.ru_stime - before.ru_stime, 3), exit=proc.returncode, ended=True)
    entry["done"] = entry["done"] or proc.returncode == 0
    put(out, stage, entry)
    return proc.returncode if proc.returncode >= 0 else 128 - proc.returncode


def report(out: Path) -> str:
    """One line per stage (state, parts, CPU hours) and the total."""
    with locked(out):
        record = load(out)
        if record["stages"]:
            save(out, record)      # the totals, from the parts
    lines = [f"{name}: {'done' if s['done'] else 'started'}, {len(s['parts'])} part(s), {s['cpu_s']:.0f} CPU-s "
             f"({s['cpu_s'] / 3600:.3f} CPU-hours)" for name, s in record["stages"].items()]
    total = record.get("cpu_s", 0.0)
    lines.append(f"in all: {total:.0f} CPU-s, {total / 3600:.3f} CPU-hours (user + system; {out / RECORD})")
    return "\n".join(lines)


def cpu(out: Path, stages: list[str]) -> dict:
    """{"stages": {stage: CPU-s}, "cpu_s": their sum} of ``stages``, each of which must be done."""
    record = load(out)
    missing = [s for s in stages if not record["stages"].get(s, {}).get("done")]
    if missing:
        raise Refused(f"{out / RECORD}: the stage {missing[0]} is not done")
    per_stage = {s: round(sum(p["user_s"] + p["sys_s"] for p in record["stages"][s]["parts"]), 3) for s in stages}
    return {"stages": per_stage, "cpu_s": round(sum(per_stage.values()), 3)}


def main(argv: list[str]) -> int:
    try:
        if len(argv) == 4 and argv[0] == "state":
            print(state(Path(argv[1]), argv[2], argv[3]))
            return 0
        if len(argv) >= 6 and argv[0] == "run" and argv[4] == "--":
            return run(Path(argv[1]), argv[2], argv[3], argv[5:])
        if len(argv) >= 3 and argv[0] == "cpu":
            print(json.dumps(cpu(Path(argv[1]), argv[2:])))
            return 0
        if len(argv) == 2 and argv[0] == "report":
            print(report(Path(argv[1])))
            return 0
        raise Refused("usage: staged_record.py state OUT STAGE SETTINGS | run OUT STAGE SETTINGS -- CMD ... | "
                      "report OUT | cpu OUT STAGE...")
    except Refused as e:
        print(f"staged: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))

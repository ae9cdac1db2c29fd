"""The same seed gives the same bytes, whatever --workers is and after an interrupted run."""
from __future__ import annotations

import hashlib
import signal
import subprocess
import sys
import time
from pathlib import Path

from conftest import TINY_ARGS, run_simgen


def file_hashes(root: Path) -> dict[str, str]:
    return {str(p.relative_to(root)): hashlib.sha1(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}


def test_two_workers_give_identical_files(tiny_dataset, tmp_path):
    out = tmp_path / "data"
    run_simgen("make", "--out", out, "--workers", "2", *TINY_ARGS)
    a, b = file_hashes(tiny_dataset), file_hashes(out)
    assert len(a) > 100 and a == b


def test_sigkill_then_resume_gives_identical_files(tiny_dataset, tmp_path):
    out = tmp_path / "data"
    cmd = [sys.executable, "-m", "simgen.cli", "make", "--out", str(out), "--workers", "1", *TINY_ARGS]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    first_part = out / ".parts" / "scene-0000.json"
    deadline = time.time() + 240
    while not first_part.exists() and time.time() < deadline and proc.poll() is None:
        time.sleep(0.05)
    assert proc.poll() is None, "the run ended before it could be interrupted"
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert not (out / "v1.0-sim").exists(), "tables must not exist before every scene is done"
    run_simgen("make", "--out", out, "--workers", "1", *TINY_ARGS)
    assert file_hashes(out) == file_hashes(tiny_dataset)


def test_other_settings_in_the_same_out_are_refused(tiny_dataset, tmp_path):
    import shutil
    copy = tmp_path / "copy"
    shutil.copytree(tiny_dataset, copy)
    proc = run_simgen("make", "--out", copy, "--preset", "tiny", "--scenes", "2", "--samples-per-scene", "3",
                      "--seed", "8", "--quiet", check=False)
    assert proc.returncode == 2 and "other settings (differing: seed)" in proc.stderr


def test_a_damaged_part_is_named_and_nothing_is_merged(tiny_dataset, tmp_path):
    """A part file without a table (damaged, or from another simgen version) stops the merge with
    one line naming it; the tables already written are left as they were."""
    import json
    import shutil
    copy = tmp_path / "copy"
    shutil.copytree(tiny_dataset, copy)
    part = copy / ".parts" / "scene-0001.json"
    records = json.loads(part.read_text())
    del records["lidarseg"]
    part.write_text(json.dumps(records))
    before = file_hashes(copy / "v1.0-sim")
    proc = run_simgen("make", "--out", copy, *TINY_ARGS, check=False)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert f"{part}: a scene part without lidarseg records" in proc.stderr
    assert file_hashes(copy / "v1.0-sim") == before

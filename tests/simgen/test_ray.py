"""`simgen make --ray`: the bytes of the local pool on a local Ray instance (loopback only), also
after the driver or a worker process was killed mid-run, and on a cluster started with `ray
start`; no process is left behind; bad input is one line and exit 2, with nothing written."""
from __future__ import annotations

import contextlib
import importlib.util
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest

from conftest import TINY_ARGS
from test_determinism import file_hashes

needs_ray = pytest.mark.skipif(importlib.util.find_spec("ray") is None,
                               reason="the optional extra 'ray' is not installed (pip install -e .[ray])")


def make_ray(out: Path, *args, env: dict | None = None, driver: list[str] | None = None) -> int:
    """`simgen make --out OUT --ray ...` as a user runs it, in a session of its own. Returns the
    driver's pid, which is that session's id: every process the run starts (Ray's included)
    belongs to it, even once its parent is gone. ``driver``: the command that takes the
    arguments after ``make``, instead of `python -m simgen.cli make`."""
    driver = driver or [sys.executable, "-m", "simgen.cli", "make"]
    proc = subprocess.Popen([*driver, "--out", str(out), "--ray", *map(str, args)],
                            env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    stdout, stderr = proc.communicate(timeout=600)
    assert proc.returncode == 0, f"simgen make --ray failed ({proc.returncode}):\n{stderr}"
    assert "simgen: 2 scenes, 6 samples," in stdout
    return proc.pid


def processes_in_session(sid: int) -> dict[int, str]:
    """The live (not zombie) processes of a session, with their names."""
    found = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            text = stat.read_text()
        except OSError:        # gone meanwhile
            continue
        state, _ppid, _group, session = text[text.rindex(")") + 2:].split()[:4]
        if int(session) == sid and state != "Z":
            found[int(stat.parent.name)] = text[text.index("(") + 1:text.rindex(")")]
    return found


def assert_nothing_left(sid: int, within_s: float = 30.0, tolerate: tuple[str, ...] = ()) -> None:
    """No process of the run's session survives it, but those whose name starts with one of
    ``tolerate``: they are ended here."""
    deadline = time.time() + within_s
    while True:
        left = processes_in_session(sid)
        unexpected = {pid: name for pid, name in left.items() if not name.startswith(tolerate)}
        if not unexpected or time.time() > deadline:
            break
        time.sleep(0.2)
    for pid in left:           # leave a clean machine, failing or not
        with contextlib.suppress(ProcessLookupError):
            os.kill(pid, signal.SIGKILL)
    assert not unexpected, f"processes left by the run: {unexpected}"


def part_stats(root: Path) -> dict[str, tuple[int, int]]:
    """Inode and mtime of each finished scene's table part (a rewrite changes both)."""
    return {p.name: (p.stat().st_ino, p.stat().st_mtime_ns) for p in (root / ".parts").glob("scene-*.json")}


@needs_ray
def test_ray_gives_the_bytes_of_the_local_pool(tiny_dataset, tmp_path):
    out = tmp_path / "data"
    driver = make_ray(out, "--workers", "2", *TINY_ARGS)
    a, b = file_hashes(tiny_dataset), file_hashes(out)
    assert len(a) > 100 and a == b
    assert_nothing_left(driver)


@needs_ray
def test_killed_driver_resumes_without_redoing_finished_scenes(tiny_dataset, tmp_path):
    out = tmp_path / "data"
    # One CPU: the scenes run one after the other, so the driver dies with scene 1 in flight.
    cmd = [sys.executable, "-m", "simgen.cli", "make", "--out", str(out), "--ray", "--workers", "1", *TINY_ARGS]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    deadline = time.time() + 240
    while not part_stats(out) and time.time() < deadline and proc.poll() is None:
        time.sleep(0.05)
    assert proc.poll() is None, "the run ended before it could be interrupted"
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    finished = part_stats(out)
    assert list(finished) == ["scene-0000.json"] and not (out / "v1.0-sim").exists()
    driver = make_ray(out, "--workers", "2", *TINY_ARGS)
    assert file_hashes(out) == file_hashes(tiny_dataset)
    after = part_stats(out)
    assert len(after) == 2 and after["scene-0000.json"] == finished["scene-0000.json"], \
        "a finished scene was made again"
    assert_nothing_left(driver)
    # Ray's dashboard and runtime-env agents of the killed instance take a minute to give up on
    # its dead GCS before they exit by themselves (measured: 61 s); the rest must be gone.
    assert_nothing_left(proc.pid, tolerate=("ray::DashboardA", "ray::RuntimeEnv"))


# A driver whose Ray task kills its own worker process (SIGKILL) at its first attempt at scene 1,
# after making the scene and before returning it. The task is replaced before `make` connects to
# Ray; defined in __main__, it travels to the workers by value, and the real task it wraps by
# reference (the workers import the unpatched simgen.ray_backend).
KILLING_DRIVER = """
import os, signal, sys
from pathlib import Path
from simgen import ray_backend
from simgen.cli import main

marker = Path(sys.argv[1])
make_scene = ray_backend.scene_task

def scene_task_killed_once(s, idx, threads):
    records = make_scene(s, idx, threads)
    if idx == 1 and not marker.exists():
        marker.touch()
        os.kill(os.getpid(), signal.SIGKILL)
    return records

ray_backend.scene_task = scene_task_killed_once
sys.exit(main(["make", *sys.argv[2:]]))
"""


@needs_ray
def test_killed_worker_is_retried_by_ray(tiny_dataset, tmp_path):
    """The worker making scene 1 is killed after making it, before returning its records; Ray
    reruns the task on a new worker process and the dataset is still the same bytes."""
    out, marker = tmp_path / "data", tmp_path / "killed"
    driver = make_ray(out, "--workers", "2", *TINY_ARGS, driver=[sys.executable, "-c", KILLING_DRIVER, str(marker)])
    assert marker.exists(), "the worker was not killed"
    assert file_hashes(out) == file_hashes(tiny_dataset)
    assert_nothing_left(driver)


@needs_ray
def test_joins_an_existing_cluster(tiny_dataset, tmp_path):
    """`ray start --head` (on the loopback interface, 2 CPUs), then `make --ray HOST:PORT`
    joins it: the same bytes. Its workers are the cluster's, started by `ray start`."""
    port = free_port()
    # Ray would replace 127.0.0.1 by the machine's address; this keeps every process on loopback.
    # Token authentication is left out, as on a cluster started without RAY_AUTH_MODE=token
    # (`ray start` turns it on by itself only where ~/.ray holds a token).
    env = {**os.environ, "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER": "0", "RAY_AUTH_MODE": "disabled"}
    ray_cli = Path(sys.executable).with_name("ray")
    # Its own temporary folder, short: Ray's socket paths inside it must fit in 107 bytes.
    ray_tmp = tempfile.mkdtemp(prefix="ray-", dir="/tmp")
    head = subprocess.Popen([str(ray_cli), "start", "--head", "--block", f"--port={port}", "--node-ip-address=127.0.0.1",
                             "--num-cpus=2", "--include-dashboard=false", "--disable-usage-stats", f"--temp-dir={ray_tmp}"],
                            env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    try:
        deadline = time.time() + 120
        while not answers(port) and time.time() < deadline and head.poll() is None:
            time.sleep(0.2)
        assert head.poll() is None and answers(port), "the Ray head did not start"
        out = tmp_path / "data"
        driver = make_ray(out, f"127.0.0.1:{port}", "--workers", "1", *TINY_ARGS, env=env)
        assert file_hashes(out) == file_hashes(tiny_dataset)
        assert_nothing_left(driver)
    finally:
        # The head's process group holds all it started but the workers, which end with its
        # raylet; the check below covers its whole session. A SIGTERM would drain for 30 s first.
        with contextlib.suppress(ProcessLookupError):
            os.killpg(head.pid, signal.SIGKILL)
        head.wait(timeout=60)
        shutil.rmtree(ray_tmp, ignore_errors=True)
    assert_nothing_left(head.pid)


def free_port() -> int:
    """A loopback port with nothing listening on it (now)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def answers(port: int) -> bool:
    try:
        socket.create_connection(("127.0.0.1", port), timeout=1).close()
        return True
    except OSError:
        return False


def _bad_ray(tmp_path, *args, python_prefix: str = "") -> tuple[str, float]:
    """Run `make` with bad --ray input: exit 2, one line without a traceback, nothing written.
    Returns that line and the seconds it took."""
    out = tmp_path / "out"
    argv = ["make", "--out", str(out), "--preset", "tiny", "--scenes", "1", "--quiet", *args]
    code = f"import sys; {python_prefix}from simgen.cli import main; sys.exit(main({argv!r}))"
    t = time.perf_counter()
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    seconds = time.perf_counter() - t
    lines = [ln for ln in proc.stderr.strip().splitlines() if ln.strip()]
    assert proc.returncode == 2, proc.stderr
    assert "Traceback" not in proc.stderr and len(lines) == 1, proc.stderr
    assert not out.exists(), "nothing may be written on bad input"
    return lines[0], seconds


def test_ray_without_the_extra_names_it(tmp_path):
    # None in sys.modules makes `import ray` fail, as when the extra is not installed.
    line, _ = _bad_ray(tmp_path, "--ray", python_prefix="sys.modules['ray'] = None; ")
    assert line == "simgen: error: --ray needs the optional extra 'ray': pip install -e .[ray]"


@needs_ray
def test_unreachable_ray_cluster_is_one_line(tmp_path):
    port = free_port()
    line, seconds = _bad_ray(tmp_path, "--ray", f"127.0.0.1:{port}")
    assert line == (f"simgen: error: --ray 127.0.0.1:{port}: cannot reach the Ray cluster at "
                    f"127.0.0.1:{port} (Connection refused)")
    assert seconds < 20


@needs_ray
def test_address_without_a_ray_cluster_is_one_line(tmp_path):
    """A port that accepts connections but speaks no gRPC (a web server, say): Ray itself would
    retry it for many minutes."""
    with socket.socket() as server:
        server.bind(("127.0.0.1", 0))
        server.listen()
        port = server.getsockname()[1]
        line, seconds = _bad_ray(tmp_path, "--ray", f"127.0.0.1:{port}")
    assert line == (f"simgen: error: --ray 127.0.0.1:{port}: no Ray cluster answers at 127.0.0.1:{port} (it "
                    f"accepts connections but completes no gRPC handshake within 10 s)")
    assert seconds < 30


@pytest.mark.parametrize("address", ["nohost", "host:", "host:99999", "a b:1"])
def test_malformed_ray_address(tmp_path, address):
    line, _ = _bad_ray(tmp_path, "--ray", address)
    assert f"--ray {address!r}: give auto or HOST:PORT" in line

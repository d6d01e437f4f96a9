"""`up`'s supervisor: restart backoff that resets after healthy running, and `--listen`."""
from __future__ import annotations

import argparse

import pytest

from ballbot_vision.cli import OPENCV_POOL_SLEEPS, build_parser, up_endpoints
from common.errors import BallbotError
from common.supervisor import INITIAL_BACKOFF_S, Child, Supervisor


class Exited:
    """A child process that has exited with `code` (poll() as subprocess.Popen's)."""

    def __init__(self, code: int = 1):
        self.returncode = code

    def poll(self) -> int:
        return self.returncode


def crash(sup: Supervisor, c: Child, ran_s: float, now: float) -> float:
    """c dies after running ran_s; -> the delay until its restart."""
    import common.supervisor as S

    c.proc, c.started_at = Exited(), now - ran_s
    real = S.time.monotonic
    S.time.monotonic = lambda: now
    try:
        assert sup._restart_dead() is None
    finally:
        S.time.monotonic = real
    return c.next_start - now


def test_backoff_grows_in_a_crash_loop_and_resets_after_healthy_running():
    sup = Supervisor(healthy_after_s=30.0)
    c = Child("rectify", [])
    sup.children.append(c)
    delays = [crash(sup, c, ran_s=0.2, now=1000.0 + 100 * i) for i in range(5)]
    assert delays == [0.5, 1.0, 2.0, 4.0, 8.0]
    # it then runs fine for half an hour and crashes once: no 16 s wait
    assert crash(sup, c, ran_s=1800.0, now=5000.0) == INITIAL_BACKOFF_S
    assert c.restarts == 6


def _up_args(*argv: str) -> argparse.Namespace:
    return build_parser().parse_args(["up", *argv])


def test_up_listen_sets_the_router_endpoints_and_the_services_connect_on_loopback(monkeypatch):
    for var in ("BALLBOT_LISTEN", "BALLBOT_CONNECT"):
        monkeypatch.delenv(var, raising=False)
    assert up_endpoints(_up_args()) == (["tcp/127.0.0.1:7447"], "tcp/127.0.0.1:7447")
    assert up_endpoints(_up_args("--connect", "tcp/127.0.0.1:9000")) == (["tcp/127.0.0.1:9000"], "tcp/127.0.0.1:9000")
    assert up_endpoints(_up_args("--listen", "tcp/0.0.0.0:7447")) == (["tcp/0.0.0.0:7447"], "tcp/127.0.0.1:7447")
    assert up_endpoints(_up_args("--listen", "tcp/0.0.0.0:7447", "--listen", "tcp/[::]:7448")) == \
        (["tcp/0.0.0.0:7447", "tcp/[::]:7448"], "tcp/127.0.0.1:7447")
    assert up_endpoints(_up_args("--listen", "tcp/192.168.1.5:7447")) == (["tcp/192.168.1.5:7447"],
                                                                          "tcp/192.168.1.5:7447")
    monkeypatch.setenv("BALLBOT_LISTEN", "tcp/0.0.0.0:7500")
    assert up_endpoints(_up_args()) == (["tcp/0.0.0.0:7500"], "tcp/127.0.0.1:7500")
    with pytest.raises(BallbotError, match="fixed port"):
        up_endpoints(_up_args("--listen", "tcp/0.0.0.0:0"))


def test_later_stages_run_ahead_of_earlier_ones():
    from ballbot_vision.cli import PIPELINE, stage_nice

    assert [stage_nice(s) for s in PIPELINE] == [3, 2, 1, 0]  # capture ... segmenter
    assert stage_nice("router") == 0 and stage_nice("viewer") == 0


def test_a_child_runs_at_the_supervisors_nice_plus_its_offset(tmp_path):
    from helpers import free_port

    def nice_of(pid: int) -> int:
        with open(f"/proc/{pid}/stat") as f:
            return int(f.read().rsplit(")", 1)[1].split()[16])

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    sup = Supervisor(nice=2, stop_timeout_s=10.0)
    sup.add("router", ["run", "router", "--listen", endpoint, "--robot-id", "nice"], nice_offset=3)
    try:
        sup.start_all()
        assert nice_of(sup.children[0].proc.pid) == 5
    finally:
        sup.stop_all()


def test_a_missing_dependency_disables_an_optional_child_and_stops_a_required_one():
    """Exit status 3 (common/errors.py MissingDependency): installing is the fix, not restarting."""
    sup = Supervisor()
    viewer, capture = Child("viewer", [], optional=True), Child("capture", [])
    sup.children += [viewer, capture]
    viewer.proc = Exited(3)
    assert sup._restart_dead() is None and viewer.disabled and viewer.proc is None
    assert sup._restart_dead() is None and viewer.proc is None and viewer.restarts == 0  # never started again
    capture.proc = Exited(3)
    assert sup._restart_dead() == "capture"


@pytest.mark.system
def test_up_viewer_without_aiohttp_keeps_the_pipeline_and_says_what_to_install(tmp_path):
    """Issue 25: a missing optional dependency stopped every service of `up --viewer`. Now the viewer
    alone is disabled (once: no restart loop) before it ever says it is up, the log names the extra to
    install, and the pipeline keeps publishing fresh obstacle lists. aiohttp is hidden from the
    services by a package of that name earlier on their path that fails to import, as a missing
    one does."""
    import os
    import time

    from helpers import Collector, Up, free_port

    from common.keys import topic
    from common.messages import ObstacleList

    hidden = tmp_path / "hide" / "aiohttp"
    hidden.mkdir(parents=True)
    (hidden / "__init__.py").write_text("raise ImportError(\"No module named 'aiohttp'\", name='aiohttp')\n")
    env = {"PYTHONPATH": os.pathsep.join(filter(None, [str(hidden.parent), os.environ.get("PYTHONPATH")])),
           "BALLBOT_VIEWER_PORT": str(free_port())}
    up = Up(robot_id="noaiohttp", extra_env=env, extra_args=["--viewer"])
    lists = Collector(ObstacleList)
    try:
        with up.session() as s:
            s.declare_subscriber(topic("obstacles").key(up.robot_id), lists)
            assert lists.wait_for(lambda items: sum(not m.stale for m in items) >= 20, 180), \
                up.log_path.read_text()[-3000:]
            n = len(lists.items)
            t0 = time.monotonic()
            assert lists.wait_for(lambda items: sum(not m.stale for m in items[n:]) >= 30, 120)
            seconds = time.monotonic() - t0
        log = up.log_path.read_text()
        assert up.proc.poll() is None, "up stopped"
    finally:
        up.stop()
    viewer_starts = log.count("started viewer")
    print(f"up --viewer without aiohttp: {len(lists.items)} obstacle lists ({sum(not m.stale for m in lists.items)} "
          f"fresh; 30 new ones in {seconds:.1f} s after the viewer was disabled); "
          f"viewer started {viewer_starts} time(s)")
    assert "viewer is disabled" in log and "pip install 'ballbot-vision[viewer]'" in log
    assert viewer_starts == 1, log[-3000:]
    up_lines = [line for line in log.splitlines(True) if line.rstrip().endswith(f"up (robot {up.robot_id})")]
    assert " viewer " not in "".join(up_lines)


# what OpenCV saw when the process loaded it: a fresh interpreter runs the CLI as a process would,
# with `run` and `up` stopped where they would start the services, and OpenCV imported at the latest
# after it (where an offline command would). -> the environment at cv2's first import, as JSON.
OPENCV_POOL_PROBE = r'''
import json, os, sys
import ballbot_vision.cli as cli
seen = {}
class Watch:
    def find_spec(self, name, path=None, target=None):
        if name == "cv2" and not seen:
            seen.update({k: os.environ.get(k) for k in cli.OPENCV_POOL_SLEEPS})
sys.meta_path.insert(0, Watch())
cli.cmd_run = cli.cmd_up = lambda args: 0
cli.main(sys.argv[1:])
import cv2  # noqa: F401
print(json.dumps(seen))
'''


def opencv_pool_env(argv: list[str], **env: str) -> dict:
    """The OpenCV pool variables a process started with argv had when it loaded OpenCV, in an
    environment without them but for env."""
    import json
    import os
    import subprocess
    import sys

    clean = {k: v for k, v in os.environ.items() if k not in OPENCV_POOL_SLEEPS}
    run = subprocess.run([sys.executable, "-c", OPENCV_POOL_PROBE, *argv], env=dict(clean, **env),
                         capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    return json.loads(run.stdout.strip().splitlines()[-1])


@pytest.mark.parametrize("argv", [["run", "disparity"], ["run", "segmenter"], ["up"]])
def test_a_service_process_lets_opencvs_threads_sleep_between_frames_unless_the_user_says(argv):
    assert opencv_pool_env(argv) == {"OPENCV_THREAD_POOL_ACTIVE_WAIT_WORKER": "0",
                                     "OPENCV_THREAD_POOL_ACTIVE_WAIT_MAIN": "0"}
    assert opencv_pool_env(argv, OPENCV_THREAD_POOL_ACTIVE_WAIT_WORKER="500") == {
        "OPENCV_THREAD_POOL_ACTIVE_WAIT_WORKER": "500", "OPENCV_THREAD_POOL_ACTIVE_WAIT_MAIN": "0"}


def test_offline_commands_leave_opencvs_pool_as_opencv_sets_it():
    """`bench` measures OpenCV alone as OpenCV comes (a peer's default settings) in its own process."""
    assert opencv_pool_env(["keys"]) == {"OPENCV_THREAD_POOL_ACTIVE_WAIT_WORKER": None,
                                         "OPENCV_THREAD_POOL_ACTIVE_WAIT_MAIN": None}

"""The robot's external endpoint (deploy/zenoh/gateway.json5): TLS with client certificates,
user/password authentication and access control, with certificates from deploy/make-certs.sh.

Real processes on free loopback ports, as on the robot: an internal router (plain TCP, the robot's
own services), the gateway router started from the committed gateway.json5 (only ports and the
certificate folder rewritten), the robot's pipeline on the internal router with no onboard
fallback, and one offboard disparity worker that connects through the gateway with its rendered
client config. Obstacles flowing fresh therefore prove that an authenticated worker reads frames
(its work items) through the secured endpoint; the rest checks who else can do what there.
"""
from __future__ import annotations

import os
import re
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from helpers import REPO, free_port, wait_port

from common import codec
from common.errors import ConnectError
from common.keys import topic
from common.messages import ObstacleList
from common.supervisor import stop_processes
from common.zenoh_session import ZenohOptions, open_session

pytestmark = pytest.mark.system
RID = "sec"
ROBOT_KEY = b"the-robots-own-calibration-key"
NOTHING_S = 3.0  # bounded wait for "nothing arrives" (stated; everything else waits on events)


class Counter:
    """Counts samples per key prefix; wait(pred) blocks until pred(self) or the deadline."""

    def __init__(self) -> None:
        self.keys: list[str] = []
        self.payloads: list[bytes] = []
        self.cond = threading.Condition()

    def __call__(self, sample) -> None:
        with self.cond:
            self.keys.append(str(sample.key_expr))
            self.payloads.append(sample.payload.to_bytes())
            self.cond.notify_all()

    def wait(self, pred, timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        with self.cond:
            while not pred(self):
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self.cond.wait(min(left, 0.5))
            return True


@pytest.fixture(scope="module")
def robot(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("security")
    certs = tmp / "certs"
    # The documented command, with the test's folder for the rendered client configs.
    subprocess.run(["bash", str(REPO / "deploy/make-certs.sh"), "--out", str(certs), "--certs-path", str(certs),
                    "--client", "worker", "--client", "viewer", "--client", "pc1:worker"],
                   check=True, capture_output=True, timeout=60)
    internal, external = free_port(), free_port()
    text = (REPO / "deploy/zenoh/gateway.json5").read_text()
    assert "tcp/router:7447" in text and "tls/0.0.0.0:7448" in text
    text = (text.replace("/etc/zenoh-certs", str(certs))
                .replace("tcp/router:7447", f"tcp/127.0.0.1:{internal}")
                .replace("tls/0.0.0.0:7448", f"tls/127.0.0.1:{external}"))
    gateway_conf = tmp / "gateway.json5"
    gateway_conf.write_text(text)

    procs: dict[str, subprocess.Popen] = {}
    env = dict(os.environ, BALLBOT_LOG="INFO", PYTHONUNBUFFERED="1", BALLBOT_LEASE_MS="2000")
    env.pop("BALLBOT_ZENOH_CONFIG", None)
    env["BALLBOT_CALIBRATION_KEY"] = ROBOT_KEY.decode()  # the robot's containers share one (compose)

    def start(name: str, *args: str) -> subprocess.Popen:
        log = open(tmp / f"{name}.log", "w")
        p = subprocess.Popen([sys.executable, "-m", "ballbot_vision.cli", "run", *args, "--robot-id", RID],
                             stdout=log, stderr=subprocess.STDOUT, env=env, cwd=REPO)
        procs[name] = p
        return p

    try:
        wait_port(internal, start("router", "router", "--listen", f"tcp/127.0.0.1:{internal}"))
        wait_port(external, start("gateway", "router", "--zenoh-config", str(gateway_conf)))
        c = ["--connect", f"tcp/127.0.0.1:{internal}", "--mode", "client"]
        start("capture", "capture", *c, "--rate-hz", "10", "--preload", "4")
        start("rectify", "rectify", *c)
        start("dispatch", "disparity", *c, "--fallback", "none", "--max-age-ms", "1500")
        start("segmenter", "segmenter", *c)
        worker_env = {k: v for k, v in env.items() if k != "BALLBOT_CALIBRATION_KEY"}  # offboard: no key
        log = open(tmp / "worker.log", "w")
        procs["worker"] = subprocess.Popen(
            [sys.executable, "-m", "ballbot_vision.cli", "run", "disparity", "--role", "worker", "--robot-id", RID,
             "--zenoh-config", str(certs / "pc1.json5"), "--mode", "client", "--connect", f"tls/127.0.0.1:{external}"],
            stdout=log, stderr=subprocess.STDOUT, env=worker_env, cwd=REPO)
        yield {"certs": certs, "internal": f"tcp/127.0.0.1:{internal}", "external": f"tls/127.0.0.1:{external}",
               "tmp": tmp, "procs": procs}
    finally:
        stop_processes(procs, 10.0)


def internal_session(robot):
    return open_session(ZenohOptions(mode="client", connect=[robot["internal"]], listen=[]))


def external_session(robot, config: str | None, mode: str = "client"):
    return open_session(ZenohOptions(mode=mode, connect=[robot["external"]],
                                     listen=["tcp/127.0.0.1:0"] if mode == "peer" else [],
                                     config_file=config))


def fresh_obstacles(c: Counter, n: int) -> bool:
    lists = [codec.decode(p, ObstacleList) for p in c.payloads]
    return sum(not m.stale for m in lists) >= n


def test_authenticated_worker_computes_frames_through_the_gateway(robot):
    """Fallback is off: fresh obstacle lists exist only if the worker behind TLS gets frames.
    A viewer (read-only user) sees them through the gateway."""
    seen = Counter()
    with external_session(robot, str(robot["certs"] / "viewer.json5")) as viewer:
        viewer.declare_subscriber(topic("obstacles").key(RID), seen)
        ok = seen.wait(lambda c: fresh_obstacles(c, 5), 120)
    assert ok, (f"no fresh obstacle lists through the gateway in 120 s; logs in {robot['tmp']}: "
                + (robot["tmp"] / "worker.log").read_text()[-2000:])
    assert robot["procs"]["worker"].poll() is None


def _config_with(robot, tmp: Path, name: str, edit) -> str:
    text = edit((robot["certs"] / "pc1.json5").read_text())
    path = tmp / name
    path.write_text(text)
    return str(path)


@pytest.mark.parametrize("case", ["no credentials (client)", "no credentials (peer)", "wrong password",
                                  "password but no client certificate", "certificate but no password",
                                  "plain tcp to the tls port"])
def test_without_credentials_nothing_connects(robot, tmp_path, case):
    certs = robot["certs"]
    ca_only = ('{transport: {link: {tls: {root_ca_certificate: "%s"}}}}' % (certs / "ca.pem"))
    if case.startswith("no credentials"):
        (tmp_path / "ca.json5").write_text(ca_only)
        config, mode, endpoint = str(tmp_path / "ca.json5"), case.split("(")[1][:-1], robot["external"]
    elif case == "wrong password":
        config = _config_with(robot, tmp_path, "c.json5", lambda t: re.sub(r'password: "\w+"', 'password: "guess"', t))
        mode, endpoint = "client", robot["external"]
    elif case == "password but no client certificate":
        config = _config_with(robot, tmp_path, "c.json5",
                              lambda t: re.sub(r"\s*connect_(certificate|private_key): .*", "", t)
                              .replace("enable_mtls: true", "enable_mtls: false"))
        mode, endpoint = "client", robot["external"]
    elif case == "certificate but no password":
        config = _config_with(robot, tmp_path, "c.json5", lambda t: re.sub(r"usrpwd: \{[^}]*\}", "usrpwd: {}", t))
        mode, endpoint = "client", robot["external"]
    else:
        config, mode, endpoint = None, "client", robot["external"].replace("tls/", "tcp/")
    frames = Counter()
    try:
        o = ZenohOptions(mode=mode, connect=[endpoint], listen=["tcp/127.0.0.1:0"] if mode == "peer" else [],
                         config_file=config)
        session = open_session(o)
    except ConnectError:
        return  # refused: the expected outcome for a client
    # A peer may open without any connection; it must then receive nothing and reach no one.
    with session, internal_session(robot) as inside:
        legit = Counter()
        inside.declare_subscriber("ballbot/obstacles/**", legit)
        session.declare_subscriber("ballbot/**", frames)
        deadline = time.monotonic() + NOTHING_S
        while time.monotonic() < deadline:
            session.put(topic("obstacles").key(RID), b"fake")
            time.sleep(0.2)  # a paced stream of forgeries over the stated NOTHING_S window
        # (a session's own puts reach its own subscriber locally: those are not received data)
        received = [k for k, p in zip(frames.keys, frames.payloads) if p != b"fake"]
        assert not received, f"{case}: received {received[:3]}"
        assert b"fake" not in legit.payloads, f"{case}: a forged obstacle list got in"


def test_authenticated_users_get_only_what_their_role_allows(robot):
    """Through the gateway, with valid credentials: a worker gets no camera frames and cannot
    publish obstacles; a viewer gets obstacles but no frames; the robot's own services (internal
    endpoint) get everything, so "nothing" above is not a dead pipeline."""
    certs = robot["certs"]
    with internal_session(robot) as inside, \
            external_session(robot, str(certs / "worker.json5")) as worker, \
            external_session(robot, str(certs / "viewer.json5")) as viewer:
        inside_frames, inside_obst = Counter(), Counter()
        inside.declare_subscriber("ballbot/*/frames/**", inside_frames)
        inside.declare_subscriber("ballbot/obstacles/**", inside_obst)
        worker_frames, viewer_frames, viewer_obst, viewer_work = Counter(), Counter(), Counter(), Counter()
        worker.declare_subscriber("ballbot/*/frames/**", worker_frames)
        viewer.declare_subscriber("ballbot/*/frames/**", viewer_frames)
        viewer.declare_subscriber("ballbot/*/work/**", viewer_work)
        viewer.declare_subscriber("ballbot/obstacles/**", viewer_obst)
        assert inside_frames.wait(lambda c: len(c.keys) >= 5, 60), "no frames on the internal router"
        assert viewer_obst.wait(lambda c: len(c.keys) >= 3, 60), "viewer gets no obstacle lists"
        forged = b"forged by an authenticated worker"
        deadline = time.monotonic() + NOTHING_S
        while time.monotonic() < deadline:
            worker.put(topic("obstacles").key(RID), forged)
            viewer.put(topic("obstacles").key(RID), forged)
            time.sleep(0.2)  # paced forgeries over the stated NOTHING_S window
        # everything above has had NOTHING_S to arrive
        assert not worker_frames.keys, f"worker read camera frames: {worker_frames.keys[:3]}"
        assert not viewer_frames.keys and not viewer_work.keys, "viewer read frames or work items"
        assert forged not in inside_obst.payloads, "a forged obstacle list reached the robot"
        assert len(inside_frames.keys) > 5 and len(inside_obst.keys) >= 3


def _status_json(robot) -> dict:
    import json

    r = subprocess.run([sys.executable, "-m", "ballbot_vision.cli", "status", "--connect", robot["internal"],
                        "--mode", "client", "--robot", RID, "--json", "--wait", "4"],
                       capture_output=True, text=True, timeout=120, cwd=REPO)
    return json.loads(r.stdout)


def _healthcheck(robot, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "ballbot_vision.cli", "healthcheck", "--connect", robot["internal"],
                           "--robot-id", RID, "--timeout", "8", *args], capture_output=True, text=True, timeout=120,
                          cwd=REPO)


@pytest.mark.slow
def test_a_worker_cannot_pose_as_a_robot_service_in_status_or_healthcheck(robot):
    """Issue 25: the worker role could write the dispatcher's stats key, so forged stats could make
    `status` and `healthcheck` lie. Now the worker role writes only the workers' own stats key: its
    forgeries on the dispatcher's and the segmenter's keys never reach the robot, and what it says on
    its own key (even claiming to be a healthy robot service on this host) is shown as
    self-reported and never counted: `healthcheck --service ros2` (no such service runs) still fails."""
    import json
    import socket

    from common.messages import ServiceStats

    certs = robot["certs"]
    forged_status = "FORGED by an authenticated worker"
    # the dispatcher's real instance (read inside here; an attacker would guess it or learn it elsewhere)
    with internal_session(robot) as inside:
        stats = Counter()
        inside.declare_subscriber(topic("stats").pattern(RID), stats)
        assert stats.wait(lambda c: any("/stats/disparity/" in k for k in c.keys), 60), "no dispatcher stats"
        dispatcher = next(k for k in stats.keys if "/stats/disparity/" in k).rsplit("/", 1)[1]

        def forged(service: str, instance: str, role: str = "") -> bytes:
            return codec.encode(ServiceStats(robot_id=RID, service=service, role=role, instance=instance,
                                             host=socket.gethostname(), pid=1, stamp_ns=time.time_ns(), uptime_s=999,
                                             rate_hz=30.0, proc_ms_p50=5.0, age_ms_p50=40.0, processed=999,
                                             published=999, drops=0, decode_errors=0, errors=0,
                                             status=forged_status, health="ok"))

        n0 = len(stats.keys)
        with external_session(robot, str(certs / "worker.json5")) as worker:
            done = threading.Event()

            def forge() -> None:  # a paced stream of forgeries, twice a second, while status looks
                while not done.wait(0.5):
                    worker.put(topic("stats").key(RID, service="disparity", instance=dispatcher),
                               forged("disparity", dispatcher, "dispatcher"))
                    worker.put(topic("stats").key(RID, service="segmenter", instance="forged"),
                               forged("segmenter", "forged"))
                    worker.put(topic("worker_stats").key(RID, instance="forged"), forged("ros2", "forged"))

            forger = threading.Thread(target=forge, daemon=True)
            forger.start()
            try:
                status = _status_json(robot)
                hc_forged = _healthcheck(robot, "--service", "ros2")
                hc_workers = _healthcheck(robot, "--worker")
                hc_robot = _healthcheck(robot, "--service", "segmenter")
            finally:
                done.set()
                forger.join(10)
        arrived = [k for k, p in zip(stats.keys[n0:], stats.payloads[n0:]) if forged_status.encode() in p]
    rows = {(r["name"], r["instance"]): r for r in status["instances"]}
    print(f"forged stats that reached the robot: {sorted(set(arrived))}")
    print(f"status: {status['pipeline']}; rows: "
          + ", ".join(f"{n}/{i[:12]} {'trusted' if r['trusted'] else 'self-reported'} {r['status'][:30]!r}"
                      for (n, i), r in rows.items()))
    print(f"healthcheck --service ros2 -> {hc_forged.returncode} ({hc_forged.stderr.strip()[:160]}); "
          f"--worker -> {hc_workers.returncode}; --service segmenter -> {hc_robot.returncode}")
    assert arrived == [topic("worker_stats").key(RID, instance="forged")] * len(arrived) and arrived, arrived
    trusted_forged = [r for r in status["instances"] if r["trusted"] and r["status"] == forged_status]
    assert not trusted_forged, trusted_forged
    f = rows[("worker", "forged")]
    assert not f["trusted"] and f["service"] == "disparity" and f["role"] == "worker"
    assert any(n == "worker" and i != "forged" and not r["trusted"] for (n, i), r in rows.items()), \
        "the real worker's own stats did not reach status through the gateway"
    assert status["pipeline"]["health"] in ("ok", "degraded") and "ros2" not in json.dumps(status["pipeline"])
    assert hc_forged.returncode == 1 and "not trusted" in hc_forged.stderr, hc_forged.stderr
    assert hc_workers.returncode == 0, hc_workers.stderr
    assert hc_robot.returncode == 0, hc_robot.stderr


def test_a_worker_cannot_publish_a_calibration_through_the_gateway(robot):
    """Calibration is configuration: no offboard user may put one (gateway ACL); rectify counts none."""
    import yaml

    from common.messages import CalibrationUpdate
    from common.signing import sign
    from cores import camera

    doc = camera.calibration_to_dict(camera.load_calibration("lifecam-studio"))
    doc["T"] = [t / 2 for t in doc["T"]]
    with internal_session(robot) as inside, external_session(robot, str(robot["certs"] / "worker.json5")) as worker:
        seen = Counter()
        inside.declare_subscriber(topic("calibration").key(RID), seen)
        deadline = time.monotonic() + NOTHING_S
        while time.monotonic() < deadline:
            msg = CalibrationUpdate(robot_id=RID, seq=0, stamp_ns=time.time_ns(), yaml=yaml.safe_dump(doc),
                                    source="a worker")
            worker.put(topic("calibration").key(RID), codec.encode(msg))
            worker.put(topic("calibration").key(RID), codec.encode(sign(msg, b"a guessed key")))
            time.sleep(0.2)  # paced forgeries over the stated NOTHING_S window
    print(f"calibrations from the worker role that reached the robot: {len(seen.keys)}")
    assert not seen.keys

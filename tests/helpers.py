"""Shared test helpers: free ports, a running pipeline, a Zenoh session on it, waiting on events.
Import them as `from helpers import ...` (pytest puts tests/ on sys.path)."""
from __future__ import annotations

import os
import re
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

from bench.measure import free_port  # noqa: F401 (the one port picker; tests import it from here)
from common import codec
from common.zenoh_session import ZenohOptions, open_session

REPO = Path(__file__).resolve().parent.parent


def cli(*args: str) -> list[str]:
    return [sys.executable, "-m", "ballbot_vision.cli", *args]


class Collector:
    """Decodes samples of one model into a list; wait_for() blocks until a predicate holds."""

    def __init__(self, model):
        self.model = model
        self.items: list = []
        self.bad = 0
        self.cond = threading.Condition()

    def __call__(self, sample) -> None:
        try:
            msg = codec.decode(sample.payload.to_bytes(), self.model)
        except Exception:
            with self.cond:
                self.bad += 1
            return
        with self.cond:
            self.items.append(msg)
            self.cond.notify_all()

    def wait_for(self, predicate, timeout: float = 60.0) -> bool:
        deadline = time.monotonic() + timeout
        with self.cond:
            while not predicate(self.items):
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self.cond.wait(min(left, 0.5))
            return True


class Up:
    """`ballbot-vision up` on a free loopback port, as a user would start it."""

    def __init__(self, robot_id: str = "test", extra_env: dict | None = None, extra_args: list[str] | None = None):
        self.port = free_port()
        self.endpoint = f"tcp/127.0.0.1:{self.port}"
        self.robot_id = robot_id
        env = dict(os.environ, **(extra_env or {}))
        self.log_path = Path(f"/tmp/ballbot-up-{self.port}.log")
        self.log = open(self.log_path, "w")
        self.proc = subprocess.Popen(cli("up", "--connect", self.endpoint, "--robot-id", robot_id, *(extra_args or [])),
                                     stdout=self.log, stderr=subprocess.STDOUT, env=env, cwd=REPO)

    def session(self):
        return open_session(ZenohOptions(mode="peer", connect=[self.endpoint], listen=["tcp/127.0.0.1:0"]))

    def child_pids(self) -> dict[str, int]:
        text = self.log_path.read_text()
        return {m.group(1): int(m.group(2)) for m in re.finditer(r"started (\w+) \(pid (\d+)\)", text)}

    def stop(self) -> float:
        """SIGTERM, as an init system would; returns seconds until `up` exited."""
        t0 = time.monotonic()
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(30)  # up gives its services 10 s before it kills them
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self.log.close()
        return time.monotonic() - t0


def pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    # a zombie has exited; it only waits for its parent to reap it
    try:
        return Path(f"/proc/{pid}/stat").read_text().split(")")[-1].split()[0] != "Z"
    except OSError:
        return False


def wait_port(port: int, proc: subprocess.Popen, timeout: float = 30.0) -> None:
    """Until something accepts TCP connections on 127.0.0.1:port; fails early if proc exits."""
    deadline = time.monotonic() + timeout
    while True:
        try:
            socket.create_connection(("127.0.0.1", port), 0.5).close()
            return
        except OSError:
            assert proc.poll() is None, f"process exited with {proc.returncode} before listening on {port}"
            assert time.monotonic() < deadline, f"nothing listens on {port} after {timeout:g} s"
            try:
                proc.wait(0.1)  # polling a port: there is no event to wait on
            except subprocess.TimeoutExpired:
                pass


def read_mcap(path) -> tuple[dict, dict, list[tuple[str, object]]]:
    """What the Foxglove app reads: every channel's schema and encoding from the file, and every
    message decoded by that schema alone (protobuf with Google's runtime from the file's
    FileDescriptorSet, JSON checked against the file's JSON Schema)."""
    import json

    import jsonschema
    from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics.message_count > 0, f"{path}: no index: not a complete file"
        channels = {c.topic: (summary.schemas[c.schema_id].name, summary.schemas[c.schema_id].encoding,
                              c.message_encoding) for c in summary.channels.values()}
        counts = {summary.channels[cid].topic: n for cid, n in summary.statistics.channel_message_counts.items()}
        classes: dict[int, object] = {}
        decoded = []
        for schema, channel, message in reader.iter_messages():
            if schema.encoding == "protobuf":
                if schema.id not in classes:
                    pool = descriptor_pool.DescriptorPool()
                    for fd in descriptor_pb2.FileDescriptorSet.FromString(schema.data).file:
                        pool.Add(fd)
                    classes[schema.id] = message_factory.GetMessageClass(pool.FindMessageTypeByName(schema.name))
                decoded.append((channel.topic, classes[schema.id].FromString(message.data)))
            else:
                assert (schema.encoding, channel.message_encoding) == ("jsonschema", "json")
                doc = json.loads(message.data)
                jsonschema.validate(doc, json.loads(schema.data))
                decoded.append((channel.topic, doc))
    return channels, counts, decoded

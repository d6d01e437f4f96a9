"""`--source mcap`: replay a recording (`ballbot-vision record`, `mcap from-images`) so the rest of
the pipeline runs unchanged on recorded data. No Zenoh in the source itself; `connect_replay`
wires it to the node (play/pause/step commands, the recording's calibration for rectify).

Pacing: as recorded (`pace auto`, times `mcap_speed`), at `rate_hz` (`pace rate`), or as fast as
the pipeline takes them (`pace max`); `mcap_step` starts paused and publishes one pair per step
command (`ballbot-vision replay step`, or the viewer's buttons). Each replayed pair gets a new
capture stamp (now) and seq, as a camera's would; the ground truth of a synthetic recording goes
out with it. A recording whose writer was killed is replayed up to its last complete chunk.
"""
from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Iterator

from common.errors import SourceError
from common.messages import ReplayControl
from cores.recording import RecordingError
from cores.recording_reader import RecordedPair, RecordingReader, named_calibration
from services.capture.sources import CapturedPair, SourceContext

log = logging.getLogger("ballbot.capture")


class McapSource:
    name = "mcap"
    period_s = 0.0  # read() waits for each pair's due time itself (like a camera)

    def __init__(self, path: str, speed: float = 1.0, pace: str = "auto", rate_hz: float = 30.0,
                 loop: bool = False, step: bool = False, ctx: SourceContext | None = None):
        if not path:
            raise SourceError("mcap: no recording given (--mcap FILE)")
        self.ctx = ctx or SourceContext()
        try:
            # not strict: the capture service's other threads log while a frame decodes (see RecordingReader)
            self.reader = RecordingReader(path, strict_images=False)
            info = self.reader.info()
        except RecordingError as e:
            raise SourceError(f"mcap: {e}") from None
        self.total = info.pairs("raw") or info.pairs("rectified")
        if not self.total:
            topics = ", ".join(sorted(info.channels)) or "none"
            raise SourceError(f"mcap: {path} holds no stereo pairs (topics: {topics})")
        self.path = path
        self.speed = speed
        self.pace = pace
        self.rate_hz = rate_hz
        self.loop = loop
        self.ended = False
        self.scenario = ""
        self.calibration_yaml: str | None = None
        self.index = 0
        self._cond = threading.Condition()
        self._paused = step
        self._step_budget = 0
        self._index0 = 0
        # connect_replay clears this until rectify has taken the recording's calibration, so no
        # pair goes out before it can be rectified
        self.ready = threading.Event()
        self.ready.set()
        self.ready_timeout_s = 10.0
        self.on_calibration: Callable[[str], None] | None = None
        self._pairs: Iterator[RecordedPair] = self._open()
        self._first = self._next_pair()  # fail at start on an undecodable first pair
        if self._first is None:
            raise SourceError(f"mcap: {path}: no complete stereo pair could be read")
        self.calibration_yaml = self._named(self._first)
        self.calibration_name = self._name_of(self.calibration_yaml)
        log.info("mcap: replaying %s: %d %s pairs, calibration %s", path, self.total, self.reader.kind,
                 f"'{self.calibration_name}'" if self.calibration_yaml else
                 "none recorded (rectify keeps its own: set rectify.calibration)")
        self._t0_rec: int | None = None
        self._t0_wall = 0.0
        self.ctx.extra.update({"replay_total": float(self.total), "replay_index": 0.0,
                               "replay_paused": float(self._paused), "replay_speed": float(speed)})
        self._report()

    def _named(self, pair: RecordedPair) -> str | None:
        """The pair's calibration with a name (the recorded source where the file has none), so
        that rectify's log and status say which calibration the replay runs with."""
        if not pair.calibration_yaml:
            return None
        return named_calibration(pair.calibration_yaml, pair.calibration_source or f"recorded in {self.path}")

    @staticmethod
    def _name_of(yaml_text: str | None) -> str:
        from common.files import parse_yaml

        try:
            doc = parse_yaml(yaml_text or "", "calibration")
        except Exception:
            return "?"
        return str(doc.get("name") or "?") if isinstance(doc, dict) else "?"

    def _open(self) -> Iterator[RecordedPair]:
        return self.reader.pairs("auto")

    def _next_pair(self) -> RecordedPair | None:
        try:
            return next(self._pairs)
        except StopIteration:
            return None
        except RecordingError as e:
            raise SourceError(f"mcap: {e}") from None

    # -- control (any thread) ----------------------------------------------------------------------
    def control(self, cmd: ReplayControl) -> None:
        with self._cond:
            if cmd.speed is not None:
                self.speed = cmd.speed
                self._t0_rec = None  # re-anchor the clock at the next pair
            if cmd.action == "pause":
                self._paused = True
            elif cmd.action == "play":
                self._paused = False
                self._t0_rec = None
            elif cmd.action == "step":
                self._paused = True
                self._step_budget += cmd.frames
            self._cond.notify_all()
        self._report()

    def _report(self) -> None:
        state = "paused" if self._paused else "playing"
        self.ctx.extra.update({"replay_index": float(self.index), "replay_paused": float(self._paused),
                               "replay_speed": float(self.speed)})
        self.ctx.status(f"replay {state} {self.index}/{self.total} x{self.speed:g}")

    def _wait_turn(self, stamp_ns: int) -> bool:
        """Block until this pair may go out (paused: a step; playing: its due time). False: stopping."""
        stop = self.ctx.stop
        with self._cond:
            while self._paused and self._step_budget == 0:
                if stop.is_set():
                    return False
                self._cond.wait(0.2)
            stepping = self._paused
            if stepping:
                self._step_budget -= 1
        if stepping or self.pace == "max":
            return not stop.is_set()
        if self.pace == "rate":
            if self._t0_rec is None:
                self._t0_rec, self._t0_wall, self._index0 = stamp_ns, time.monotonic(), self.index
            due = self._t0_wall + (self.index - self._index0) / self.rate_hz
        else:
            if self._t0_rec is None or stamp_ns < self._t0_rec:
                self._t0_rec, self._t0_wall = stamp_ns, time.monotonic()
            due = self._t0_wall + (stamp_ns - self._t0_rec) / 1e9 / self.speed
        delay = due - time.monotonic()
        if delay > 0:
            with self._cond:  # a play/pause/speed command wakes the wait early
                self._cond.wait(delay)
            if self._t0_rec is None and not stop.is_set():  # re-anchored meanwhile: go now
                return True
        return not stop.is_set()

    def _wait_ready(self) -> bool:
        deadline = time.monotonic() + self.ready_timeout_s
        while not self.ready.is_set():
            if self.ctx.stop.is_set():
                return False
            if time.monotonic() >= deadline:
                log.warning("mcap: no rectify instance took the recording's calibration within %.0f s; "
                            "replaying anyway", self.ready_timeout_s)
                break
            self.ready.wait(0.2)
        return True

    # -- the source interface --------------------------------------------------------------------
    def read(self) -> CapturedPair | None:
        pair: RecordedPair | None
        if self._first is not None:
            if not self._wait_ready():
                return None
            pair, self._first = self._first, None
        else:
            pair = self._next_pair()
            if pair is None:
                if self.reader.truncated:
                    self.ctx.extra["replay_truncated"] = 1.0
                if not self.loop:
                    self.ended = True
                    return None
                self._pairs = self._open()
                self.index = 0
                self._t0_rec = None
                pair = self._next_pair()
                if pair is None:
                    self.ended = True
                    return None
        if not self._wait_turn(pair.stamp_ns):
            return None
        named = self._named(pair)
        if named and named != self.calibration_yaml:
            self.calibration_yaml = named  # the calibration changed during the recording
            self.calibration_name = self._name_of(named)
            if self.on_calibration is not None:
                self.on_calibration(named)
        self.scenario = pair.scenario
        self.index += 1
        self._report()
        return CapturedPair(pair.left, pair.right, t_s=pair.stamp_ns / 1e9, truth=pair.truth,
                            extra={"recorded_seq": float(pair.seq)})

    def close(self) -> None:
        with self._cond:
            self._cond.notify_all()


def connect_replay(node, source: McapSource) -> None:
    """Wire a replay to the service: play/pause/step commands from the replay_control key, and the
    recording's calibration published on the calibration key whenever a rectify instance appears
    (rectify then rectifies the recorded pairs with the calibration they were recorded with)."""
    from common import codec
    from common.keys import topic
    from common.messages import CalibrationUpdate
    from common.signing import sign

    def on_control(sample) -> None:
        cmd = node.decode_or_drop(sample.payload.to_bytes(), ReplayControl, "replay command", "control")
        if cmd is not None:
            source.control(cmd)

    node.subscribe(topic("replay_control").key(node.robot_id), on_control)
    if not source.calibration_yaml:
        return
    import zenoh

    from common.messages import ServiceStats

    source.ready.clear()
    calibration = node.declare_publisher(topic("calibration").key(node.robot_id))
    sent: dict[str, int] = {}  # rectify instance -> announcements to it
    lock = threading.Lock()

    def announce(instance: str, yaml_text: str | None = None) -> None:
        with lock:
            sent[instance] = sent.get(instance, 0) + 1
            n = sum(sent.values())
        msg = CalibrationUpdate(robot_id=node.robot_id, seq=n, stamp_ns=time.time_ns(),
                                yaml=yaml_text or source.calibration_yaml, source=f"recording {source.path}")
        calibration.put(codec.encode(sign(msg)))

    def on_rectify_alive(sample) -> None:
        if sample.kind == zenoh.SampleKind.PUT:
            announce(str(sample.key_expr).rsplit("/", 1)[-1])

    def on_rectify_stats(sample) -> None:
        # A rectify instance announces itself before it subscribes to calibrations, so the first
        # announcement can miss it: repeat (a few times) until its stats show a calibration swap.
        st = node.decode_or_drop(sample.payload.to_bytes(), ServiceStats, "rectify stats", "stats")
        if st is None or st.service != "rectify":
            return
        if st.extra.get("calibration_generation", 0) >= 1:
            source.ready.set()
        elif sent.get(st.instance, 0) < 4:
            announce(st.instance)

    def announce_all(text: str) -> None:
        for i in list(sent) or ["*"]:
            announce(i, text)

    source.on_calibration = announce_all
    node.subscribe(topic("stats").key(node.robot_id, service="rectify", instance="*"), on_rectify_stats)
    # history=True: rectify instances already alive are announced at once
    node.watch_tokens(topic("alive").key(node.robot_id, service="rectify", instance="*"), on_rectify_alive)

"""Reading a recording back (cores/recording.py says what is in it): its stereo pairs with their
calibration and truth, in order, for replay (`capture --source mcap`), `mcap to-images` and the
offline commands; layout 1 and 2 files, a newer layout refused by number, a damaged file read as
far as it goes."""
from __future__ import annotations

import itertools
import json
import logging
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from common.errors import path_error
from common.messages import GroundTruth, TruthObstacle
from cores import foxglove
from cores.recording import (
    CALIBRATION,
    LAYOUT,
    RAW_LEFT,
    RAW_RIGHT,
    RECT_CALIBRATION,
    RECT_LEFT,
    RECT_RIGHT,
    TRUTH,
    RecordingError,
)

log = logging.getLogger("ballbot.recording")


@dataclass
class RecordedPair:
    """One stereo pair read back. left/right: (H, W) grey or (H, W, 3) BGR uint8."""

    seq: int
    stamp_ns: int
    left: np.ndarray
    right: np.ndarray
    truth: list[TruthObstacle] | None = None
    scenario: str = ""
    calibration_yaml: str | None = None  # the latest calibration for these pairs recorded at or before this pair
    calibration_source: str = ""  # where that calibration came from, as recorded (a file, a profile, ...)


@dataclass
class RecordingInfo:
    path: str
    channels: dict[str, int] = field(default_factory=dict)  # topic -> message count
    start_ns: int = 0
    end_ns: int = 0
    complete: bool = True  # False: no summary (the writer was killed); counts come from a scan
    metadata: dict[str, str] = field(default_factory=dict)

    @property
    def duration_s(self) -> float:
        return max(0, self.end_ns - self.start_ns) / 1e9

    def pairs(self, kind: str = "raw") -> int:
        left, right = (RAW_LEFT, RAW_RIGHT) if kind == "raw" else (RECT_LEFT, RECT_RIGHT)
        return min(self.channels.get(left, 0), self.channels.get(right, 0))


def image_payload(topic: str, message_encoding: str, schema_name: str, schema_data: bytes, data: bytes,
                  decoder: foxglove.ProtobufDecoder, where: str) -> tuple[bytes, str]:
    """A recorded foxglove.CompressedImage -> (its image bytes, format). Layout 2: protobuf, by the
    schema the file carries; layout 1: JSON with the bytes in base64."""
    if message_encoding == "protobuf":
        try:
            msg = decoder.decode(schema_name, schema_data, data)
            return bytes(msg.data), str(msg.format)
        except Exception as e:  # protobuf's DecodeError, a schema that is not a FileDescriptorSet, ...
            raise RecordingError(f"{where}: not a {schema_name} protobuf message ({type(e).__name__})") from None
    import base64

    try:
        doc = json.loads(data)
        return base64.b64decode(doc["data"]), str(doc.get("format", "?"))
    except (KeyError, TypeError, ValueError) as e:
        raise RecordingError(f"{where}: no base64 image data ({type(e).__name__})") from None


def decode_image(data: bytes, fmt: str, where: str, strict: bool = True) -> np.ndarray:
    """Recorded image bytes -> array. strict: a JPEG or PNG that libjpeg or libpng reports damaged
    is refused (their warnings on stderr are captured for it, see common/files.py); else only an
    image that does not decode at all is."""
    from common.errors import FileError
    from common.files import imdecode_checked

    a: np.ndarray | None
    if strict:  # a damaged JPEG or PNG is refused, not decoded grey with libjpeg's warning on stderr
        try:
            a = imdecode_checked(data, where, cv2.IMREAD_UNCHANGED)
        except FileError as e:
            raise RecordingError(str(e)) from None
    else:
        a = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED) if data else None
        if a is None:
            raise RecordingError(f"{where}: {fmt} image of {len(data)} bytes does not decode")
    if a.ndim == 3 and a.shape[2] == 4:
        a = cv2.cvtColor(a, cv2.COLOR_BGRA2BGR)
    return a


def named_calibration(yaml_text: str, name: str) -> str:
    """A calibration's YAML with `name` set where it has none, so that whoever loads it (rectify,
    in its log and status) can say which calibration it is."""
    import yaml as pyyaml

    from common.files import parse_yaml

    try:
        doc = parse_yaml(yaml_text, "calibration")
    except Exception:
        return yaml_text  # whoever loads it says what is wrong with it
    if not isinstance(doc, dict) or doc.get("name") or not name:
        return yaml_text
    return pyyaml.safe_dump({"name": name, **doc}, sort_keys=False)


class RecordingReader:
    """Reads a recording back. Opening checks it is an MCAP file; a file whose writer was killed
    (no summary) is read up to its last complete chunk, with `truncated` set and a warning.
    strict_images: see decode_image (off where other threads log meanwhile: capturing stderr
    around a decode would swallow their lines)."""

    def __init__(self, path: str | Path, strict_images: bool = True):
        self.path = Path(path)
        self.strict_images = strict_images
        try:
            with open(self.path, "rb") as f:
                magic = f.read(8)
        except OSError as e:
            raise RecordingError(f"recording {path}: {path_error(e)}") from None
        if magic != b"\x89MCAP0\r\n":
            raise RecordingError(f"{path}: not an MCAP file (it starts with {magic[:8]!r})")
        self.truncated = False
        self._info: RecordingInfo | None = None

    def _messages(self, topics: list[str] | None = None) -> Iterator[tuple[str, Any, Any, Any]]:
        """(topic, mcap message, channel, schema) in log-time order where the file has an index,
        else file order."""
        from mcap.reader import make_reader

        with open(self.path, "rb") as f:
            reader = make_reader(f)
            try:
                indexed = reader.get_summary() is not None
            except Exception:  # a truncated file has no readable footer
                indexed = False
            if not indexed:
                from mcap.reader import NonSeekingReader

                f.seek(0)
                reader = NonSeekingReader(f, validate_crcs=False)
            n = 0
            try:
                for schema, channel, message in reader.iter_messages(topics=topics, log_time_order=indexed):
                    n += 1
                    yield channel.topic, message, channel, schema
            except Exception as e:  # the mcap reader raises several types at a cut-off end
                if indexed:
                    raise RecordingError(f"{self.path}: damaged after {n} messages: {e}") from None
            if not indexed and not self.truncated:
                self.truncated = True
                log.warning("%s: no index (the recorder was killed?); read %d messages up to the last "
                            "complete chunk", self.path, n)

    def info(self) -> RecordingInfo:
        if self._info is not None:
            return self._info
        from mcap.reader import make_reader

        info = RecordingInfo(str(self.path))
        summary = None
        with open(self.path, "rb") as f:
            try:
                reader = make_reader(f)
                summary = reader.get_summary()
                for m in reader.iter_metadata():
                    info.metadata.update(m.metadata)
            except Exception:
                summary = None
        if summary is not None and summary.statistics is not None:
            st = summary.statistics
            info.channels = {summary.channels[cid].topic: n for cid, n in st.channel_message_counts.items()}
            info.start_ns, info.end_ns = st.message_start_time, st.message_end_time
        else:
            info.complete = False
            times = []
            for topic, m, _, _ in self._messages():
                info.channels[topic] = info.channels.get(topic, 0) + 1
                times.append(m.log_time)
            if times:
                info.start_ns, info.end_ns = min(times), max(times)
        layout = info.metadata.get("layout", "1")
        if not layout.isdigit() or int(layout) > LAYOUT:
            raise RecordingError(f"{self.path}: recording layout {layout}, newer than this version of ballbot-vision "
                                 f"reads (layouts 1 to {LAYOUT}); update ballbot-vision to read it")
        self._info = info
        return info

    def pairs(self, kind: str = "auto") -> Iterator[RecordedPair]:
        """Stereo pairs in capture order: the raw pairs ("raw"), the rectified ones ("rectified"),
        or raw when the recording has them, else rectified ("auto"). A pair missing a half is
        skipped (counted in `unpaired`), as is one with a damaged image (logged, counted in
        `damaged`): a replay goes on past it."""
        info = self.info()
        if kind == "auto":
            kind = "raw" if info.pairs("raw") else "rectified"
        left_t, right_t = (RAW_LEFT, RAW_RIGHT) if kind == "raw" else (RECT_LEFT, RECT_RIGHT)
        if not info.pairs(kind):
            have = ", ".join(sorted(info.channels)) or "no messages"
            hint = (" (`record` keeps them with --raw true)" if kind == "raw" and info.pairs("rectified") else "")
            raise RecordingError(f"{self.path}: no {kind} stereo pairs ({left_t} and {right_t}){hint}; it holds {have}")
        self.kind = kind
        self.unpaired = 0
        self.damaged = 0
        # seq -> topic -> ((image bytes, format), log time)
        halves: dict[int, dict[str, tuple[tuple[bytes, str], int]]] = {}
        truths: dict[int, GroundTruth] = {}
        calibration: str | None = None
        calibration_source = ""
        decoder = foxglove.ProtobufDecoder()
        pending: tuple[int, int, dict] | None = None  # a complete pair waits for its truth (same log time)

        def finish(seq: int, t: int, half: dict[str, tuple[tuple[bytes, str], int]]) -> RecordedPair | None:
            where = f"{self.path}: pair seq {seq}"
            truth = truths.pop(seq, None)
            for old in [s for s in truths if s < seq]:
                del truths[old]
            try:
                left = decode_image(*half[left_t][0], f"{where} left", self.strict_images)
                right = decode_image(*half[right_t][0], f"{where} right", self.strict_images)
            except RecordingError as e:
                self.damaged += 1
                log.warning("%s; pair skipped", e)
                return None
            return RecordedPair(seq=seq, stamp_ns=t, left=left, right=right,
                                truth=None if truth is None else truth.obstacles,
                                scenario="" if truth is None else truth.scenario,
                                calibration_yaml=calibration, calibration_source=calibration_source)

        calibration_topic = CALIBRATION if kind == "raw" else RECT_CALIBRATION
        for topic, m, channel, schema in self._messages([left_t, right_t, TRUTH, calibration_topic]):
            if pending is not None and m.log_time > pending[1]:
                if (pair := finish(*pending)) is not None:
                    yield pair
                pending = None
            if topic in (calibration_topic, TRUTH):
                try:
                    doc = json.loads(m.data)
                except ValueError:
                    log.warning("%s: a %s message is not JSON; skipped", self.path, topic)
                    continue
            if topic == calibration_topic:
                calibration = doc.get("yaml") if isinstance(doc, dict) else None
                calibration_source = str(doc.get("source") or "") if isinstance(doc, dict) else ""
                continue
            if topic == TRUTH:
                try:
                    truths[m.sequence] = GroundTruth.model_validate(doc)
                except Exception:
                    log.warning("%s: a %s message does not validate; skipped", self.path, topic)
                continue
            try:
                image = image_payload(topic, channel.message_encoding, schema.name if schema else "",
                                      schema.data if schema else b"", m.data, decoder,
                                      f"{self.path}: {topic} seq {m.sequence}")
            except RecordingError as e:
                self.damaged += 1
                log.warning("%s; skipped", e)
                continue
            half = halves.setdefault(m.sequence, {})
            half[topic] = (image, m.log_time)
            if len(half) < 2:
                continue
            del halves[m.sequence]
            for old in [s for s in halves if s < m.sequence - 64]:  # a half whose partner never came
                del halves[old]
                self.unpaired += 1
            if pending is not None and (pair := finish(*pending)) is not None:
                yield pair
            pending = (m.sequence, half[left_t][1], half)
        if pending is not None and (pair := finish(*pending)) is not None:
            yield pair
        self.unpaired += len(halves)



def offline_pairs(path: str | Path, calibration: str | None = None):
    """A recording for the offline commands (`obstacles rec.mcap`): (pairs, calibration), where
    pairs yields (left label, right label, left, right, t_s, seq) in capture order, t_s from the
    recording's stamps and seq its (as the labels name it), and calibration is `calibration` (a
    file or profile) or else the recording's own, as a Calibration."""
    from common.files import parse_yaml
    from cores import camera

    reader = RecordingReader(path)
    pairs = reader.pairs("auto")  # raw pairs where recorded (they need a calibration), else the rectified ones
    first = next(pairs, None)
    if first is None:
        raise RecordingError(f"{path}: no stereo pair could be read")
    where = f"{path}: {CALIBRATION if reader.kind == 'raw' else RECT_CALIBRATION}"
    if calibration and reader.kind == "rectified":
        raise RecordingError(f"{path}: holds rectified pairs, recorded with their rectified camera: they need no "
                             f"--calibration")
    if calibration:
        cal = camera.load_calibration(calibration)
    elif first.calibration_yaml:
        cal = camera.calibration_from_dict(parse_yaml(first.calibration_yaml, where), where=where)
    else:
        raise RecordingError(f"{path}: the recording holds no calibration; give one with --calibration")

    def labelled():
        for p in itertools.chain([first], pairs):
            yield (f"{path}#{p.seq}:left", f"{path}#{p.seq}:right", p.left, p.right,
                   (p.stamp_ns - first.stamp_ns) / 1e9, p.seq)
    return labelled(), cal

"""msgpack on the wire, and numpy <-> Image payloads (raw, png, jpeg)."""
from __future__ import annotations

import math
from typing import TYPE_CHECKING, TypeVar

import msgpack
from pydantic import BaseModel, ValidationError

from common.errors import DecodeError
from common.messages import SCHEMA_VERSION, DisparityMap, Image

if TYPE_CHECKING:  # numpy is imported where images are handled: `run router` and healthcheck never need it
    import numpy as np

M = TypeVar("M", bound=BaseModel)


def encode(msg: BaseModel) -> bytes:
    return msgpack.packb(msg.model_dump(mode="python"), use_bin_type=True)


def decode(payload: bytes, model: type[M]) -> M:
    """Decode and validate; any problem becomes a DecodeError that says what was wrong."""
    try:
        doc = msgpack.unpackb(payload, raw=False, strict_map_key=False)
    except Exception as e:  # msgpack raises several unrelated types for garbage
        raise DecodeError(f"{model.__name__}: not msgpack ({type(e).__name__}: {e})") from None
    if not isinstance(doc, dict):
        raise DecodeError(f"{model.__name__}: expected a map, got {type(doc).__name__}")
    version = doc.get("schema_version")
    if version != SCHEMA_VERSION:
        raise DecodeError(f"{model.__name__}: schema_version {version!r}, this build reads {SCHEMA_VERSION}")
    try:
        return model.model_validate(doc)
    except ValidationError as e:
        first = e.errors()[0]
        where = ".".join(str(p) for p in first["loc"])
        raise DecodeError(f"{model.__name__}.{where}: {first['msg']} ({e.error_count()} error(s))") from None


# The lowest JPEG quality a pair the pipeline matches may travel or be recorded at. Measured on the 15
# scenes with the pairs through this codec (evaluation.synthetic.render_scenario's wire): from 85 the
# lists are those of raw pairs; at 80 and 75 (the recorder's default before) low-faces' plain crate left
# a list and the free space reached under it, at 60 2 more misses, at 10 7, at 1 41 and 229 floor false
# positives, with 1 list of 129 flagged: block artefacts are texture the matcher trusts.
MIN_JPEG_QUALITY = 85


def image_from_array(a: np.ndarray, encoding: str = "raw", jpeg_quality: int = 90, bilevel: bool = False) -> Image:
    """a: (H, W) or (H, W, 3) array of uint8/uint16/int16/float32. png keeps uint8/uint16 lossless;
    jpeg is uint8 only. bilevel (png of a 0/255 uint8 mask): one bit a pixel, a few kB for 640x480
    in a third of a millisecond, decoded as 0/255 again."""
    import cv2
    import numpy as np

    if a.ndim not in (2, 3) or (a.ndim == 3 and a.shape[2] != 3):
        raise ValueError(f"image must be HxW or HxWx3, got shape {a.shape}")
    channels = 1 if a.ndim == 2 else 3
    dtype = a.dtype.name if a.dtype.isnative else str(a.dtype)  # '>u2' must not pass as uint16
    if encoding == "raw":
        data = np.ascontiguousarray(a).tobytes()
    elif encoding == "png":
        if dtype not in ("uint8", "uint16"):
            raise ValueError(f"png carries uint8 or uint16, not {dtype}")
        ok, buf = cv2.imencode(".png", a, [cv2.IMWRITE_PNG_COMPRESSION, 1] + ([cv2.IMWRITE_PNG_BILEVEL, 1]
                                                                            if bilevel else []))
        data = buf.tobytes()
    elif encoding == "jpeg":
        if dtype != "uint8":
            raise ValueError(f"jpeg carries uint8, not {dtype}")
        ok, buf = cv2.imencode(".jpg", a, [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)])
        data = buf.tobytes()
    else:
        raise ValueError(f"unknown image encoding {encoding!r} (raw, png, jpeg)")
    return Image(width=a.shape[1], height=a.shape[0], channels=channels, dtype=dtype, encoding=encoding, data=data)


def array_from_image(img: Image, name: str = "image") -> np.ndarray:
    """Inverse of image_from_array; checks the payload against the stated size and dtype.
    The returned array may be read-only (it can share the message's buffer)."""
    import cv2
    import numpy as np

    shape = (img.height, img.width) if img.channels == 1 else (img.height, img.width, img.channels)
    dtype = np.dtype(img.dtype)
    if img.encoding == "raw":
        expected = math.prod(shape) * dtype.itemsize  # math.prod: np.prod costs ~10 us per call on a tuple
        if len(img.data) != expected:
            raise DecodeError(f"{name}: {len(img.data)} bytes for a {img.width}x{img.height}x{img.channels} "
                              f"{img.dtype} image, expected {expected}")
        return np.frombuffer(img.data, dtype=dtype).reshape(shape)
    a = cv2.imdecode(np.frombuffer(img.data, np.uint8), cv2.IMREAD_UNCHANGED)
    if a is None:
        raise DecodeError(f"{name}: {img.encoding} payload of {len(img.data)} bytes does not decode")
    if a.shape != shape or a.dtype != dtype:
        raise DecodeError(f"{name}: decoded {a.shape} {a.dtype}, message states {shape} {img.dtype}")
    return a


def side_images(m: DisparityMap, encodings: dict[str, str] | None = None) -> dict[str, np.ndarray]:
    """The uint8 images a disparity map carries beside it, decoded, by name ("confidence", "flat
    mask"; those it carries). Each must be one channel of uint8 of the map's size, and in
    encodings[name] where given: else a DecodeError that names it and says what it is. One check for
    the dispatcher, which vets a worker's map (and asks for each image's encoding), and the
    segmenter, which reads the map."""
    img = m.image
    out = {}
    for name, c in (("confidence", m.confidence), ("flat mask", m.flat)):
        if c is None:
            continue
        encoding = (encodings or {}).get(name, c.encoding)
        if (c.width, c.height, c.channels, c.dtype, c.encoding) != (img.width, img.height, 1, "uint8", encoding):
            raise DecodeError(f"its {name} is {c.width}x{c.height}x{c.channels} {c.dtype} {c.encoding}, expected "
                              f"{img.width}x{img.height} uint8 {encoding}")
        out[name] = array_from_image(c, f"disparity {name}")
    return out

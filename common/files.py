"""The user's files, read the same way by every command: one wording when a file is missing,
unreadable, empty, binary, truncated, corrupt or of an impossible size (a FileError, which the CLI
prints on one line and exits 2 for); natural sort (left2 before left10) for every list of files;
image folders and globs paired left/right by name.

Image decoding goes through OpenCV, but OpenCV's own stderr noise never reaches the user: libjpeg
and libpng report damage only as warnings on stderr (a truncated JPEG still decodes, grey at the
bottom), so decoding captures stderr and turns those warnings into a FileError.
"""
from __future__ import annotations

import glob
import os
import re
import sys
import tempfile
import threading
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

from common.errors import FileError

if TYPE_CHECKING:  # numpy is imported where images are decoded: reading a YAML file needs none
    import numpy as np

IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm", ".ppm", ".pnm", ".webp")

# Limits of any image or calibration image size. 8K (7680x4320, 33 MP) fits; a 1x1 image or a
# calibration that asks for 200000x200000 pixels (remap tables of ~240 GB) does not. OpenCV's own
# decoders are held to the same limits (ballbot_vision/__init__.py sets them before cv2 loads), so
# an oversized image of a format image_header_size does not read is refused before decoding.
MIN_IMAGE_SIDE = 16
MAX_IMAGE_SIDE = 16384
MAX_IMAGE_PIXELS = 40_000_000


def natural_key(text: Any) -> list:
    """Sort key so that img2 < img10 (digit runs compare as numbers, the rest case-insensitively).
    re.split with a group alternates text and digit runs, so equal positions hold equal types."""
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"([0-9]+)", str(text))]


def natural_sorted(items: Sequence[Any]) -> list:
    return sorted(items, key=natural_key)


# --- any file ------------------------------------------------------------------------------------

def check_readable(path: str | Path, what: str = "") -> Path:
    """The path of an existing, readable regular file, else a FileError in the common wording."""
    p = Path(os.path.expanduser(str(path)))
    label = f"{what} {path}" if what else str(path)
    if not p.exists():
        raise FileError(f"{label}: no such file or folder")
    if p.is_dir():
        raise FileError(f"{label}: is a folder, not a file")
    if not os.access(p, os.R_OK):
        raise FileError(f"{label}: cannot read the file (permission denied)")
    return p


def output_folder(path: str | Path, what: str = "") -> Path:
    """The folder `path`, made with its parents if missing, else a FileError naming it and why."""
    from common.errors import path_error

    p = Path(os.path.expanduser(str(path)))
    try:
        p.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise FileError(f"{what + ' ' if what else ''}{path}: {path_error(e)}") from None
    return p


def write_image(path: str | Path, image: np.ndarray, what: str = "") -> None:
    """cv2.imwrite, or a FileError naming the path (its folder missing or read-only, the disk full)."""
    import cv2

    if not cv2.imwrite(str(path), image):
        raise FileError(f"{what + ' ' if what else ''}{path}: cannot write the image")


def read_bytes(path: str | Path, what: str = "") -> bytes:
    p = check_readable(path, what)
    label = f"{what} {path}" if what else str(path)
    try:
        data = p.read_bytes()
    except OSError as e:
        raise FileError(f"{label}: cannot read the file ({e.strerror or e})") from None
    if not data:
        raise FileError(f"{label}: the file is empty")
    return data


def read_text(path: str | Path, what: str = "") -> str:
    """A text file's content; binary data (an image, a zip) or an empty file is a FileError."""
    data = read_bytes(path, what)
    label = f"{what} {path}" if what else str(path)
    if b"\x00" in data[:8192]:
        raise FileError(f"{label}: binary data, not a text file")
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as e:
        raise FileError(f"{label}: binary data, not a text file (byte {e.start} is not UTF-8)") from None


# Hostile YAML: a few hundred bytes of nested aliases ("billion laughs") expand to hundreds of
# millions of values once anything walks the document (1.6 GB for a 700-byte calibration before this
# limit), and thousands of nested brackets exhaust Python's recursion. No calibration, scenario or
# config comes near either limit.
MAX_YAML_VALUES = 200_000


def parse_yaml(text: str, label: str) -> Any:
    """YAML text -> Python (safe_load semantics). OpenCV FileStorage's `%YAML:1.0` first line,
    which YAML parsers reject, is accepted (EuRoC and OpenCV write it). Invalid YAML, aliases that
    expand to more than MAX_YAML_VALUES values and too deep nesting are a FileError naming `label`
    (and the line)."""
    import yaml

    text = re.sub(r"\A%YAML:\d+\.\d+[^\n]*\n", "", text)
    loader = yaml.SafeLoader(text)
    try:
        node = loader.get_single_node()
        if node is not None:
            n = _expanded_values(node)
            if n > MAX_YAML_VALUES:
                raise FileError(f"{label}: YAML aliases that expand to more than {MAX_YAML_VALUES} values "
                                f"({'endless' if n >= 1 << 62 else n})")
        return loader.construct_document(node) if node is not None else None
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        where = f" (line {mark.line + 1}: {getattr(e, 'problem', '') or 'syntax error'})" if mark else ""
        raise FileError(f"{label}: not valid YAML{where}") from None
    except RecursionError:
        raise FileError(f"{label}: YAML nested too deeply") from None
    finally:
        loader.dispose()


def _expanded_values(root: Any) -> int:
    """How many values the YAML node graph holds once its aliases are expanded, counted without
    expanding them (a shared node is counted once per reference, its size computed once)."""
    import yaml

    size: dict[int, int] = {}
    visiting: set[int] = set()
    stack: list[tuple[Any, bool]] = [(root, False)]
    while stack:  # post-order without recursion
        node, children_done = stack.pop()
        if id(node) in size:
            continue
        if not children_done and id(node) in visiting:  # a node that holds itself (&a [*a]): endless
            return 1 << 62
        if isinstance(node, yaml.SequenceNode):
            kids = list(node.value)
        elif isinstance(node, yaml.MappingNode):
            kids = [n for pair in node.value for n in pair]
        else:
            size[id(node)] = 1
            continue
        if children_done:
            size[id(node)] = min(1 + sum(size[id(k)] for k in kids), 1 << 62)
        else:
            visiting.add(id(node))
            stack.append((node, True))
            stack.extend((k, False) for k in kids if id(k) not in size)
    return size[id(root)]


def read_yaml(path: str | Path, what: str = "") -> Any:
    """A YAML file parsed as parse_yaml does; missing, empty, binary or hostile files are a
    FileError naming the file (and the line)."""
    return parse_yaml(read_text(path, what), f"{what} {path}" if what else str(path))


# --- images --------------------------------------------------------------------------------------

def check_image_size(width: int, height: int, where: str) -> None:
    """Refuse sizes no stereo pair can have: below MIN_IMAGE_SIDE, above MAX_IMAGE_SIDE per side or
    MAX_IMAGE_PIXELS in all."""
    if width < MIN_IMAGE_SIDE or height < MIN_IMAGE_SIDE:
        raise FileError(f"{where}: {width}x{height} pixels is too small for a stereo image "
                        f"(at least {MIN_IMAGE_SIDE}x{MIN_IMAGE_SIDE})")
    if width > MAX_IMAGE_SIDE or height > MAX_IMAGE_SIDE or width * height > MAX_IMAGE_PIXELS:
        raise FileError(f"{where}: {width}x{height} pixels is larger than this program handles "
                        f"(at most {MAX_IMAGE_SIDE} per side and {MAX_IMAGE_PIXELS // 1_000_000} megapixels)")


def image_header_size(data: bytes) -> tuple[int, int] | None:
    """(width, height) from a PNG, JPEG, PNM, BMP, TIFF or WebP header without decoding, so that a
    small file that claims a huge image (a decompression bomb, or a header cut off from its data)
    is refused, with its size, before any memory is spent; None for anything else (OpenCV's own
    pixel limit, which is ours, then refuses an oversized image before decoding it)."""
    for parse in (_png_size, _jpeg_size, _pnm_size, _bmp_size, _tiff_size, _webp_size):
        try:
            size = parse(data)
        except (IndexError, ValueError):  # a header cut short: the decoder says what is wrong
            size = None
        if size is not None:
            return size
    return None


def _png_size(data: bytes) -> tuple[int, int] | None:
    if data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) >= 24 and data[12:16] == b"IHDR":
        return int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")
    return None


def _jpeg_size(data: bytes) -> tuple[int, int] | None:
    if data[:2] != b"\xff\xd8":
        return None
    i = 2
    while i + 9 <= len(data):
        if data[i] != 0xFF:
            return None
        marker = data[i + 1]
        if marker == 0xFF:  # fill byte
            i += 1
            continue
        length = int.from_bytes(data[i + 2:i + 4], "big")
        if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):  # SOFn
            return int.from_bytes(data[i + 7:i + 9], "big"), int.from_bytes(data[i + 5:i + 7], "big")
        if marker in (0xD8, 0x01) or 0xD0 <= marker <= 0xD7:
            i += 2
            continue
        i += 2 + length
    return None


_PNM = re.compile(rb"\AP[1-6](?:\s|#[^\n]*\n)+(\d+)(?:\s|#[^\n]*\n)+(\d+)\s")


def _pnm_size(data: bytes) -> tuple[int, int] | None:
    m = _PNM.match(data[:1024])
    return (int(m.group(1)), int(m.group(2))) if m else None


def _bmp_size(data: bytes) -> tuple[int, int] | None:
    if data[:2] != b"BM" or len(data) < 26:
        return None
    if int.from_bytes(data[14:18], "little") == 12:  # OS/2 BITMAPCOREHEADER: 16-bit sides
        return int.from_bytes(data[18:20], "little"), int.from_bytes(data[20:22], "little")
    # BITMAPINFOHEADER and later: 32-bit signed sides, a negative height means rows top-down
    return (abs(int.from_bytes(data[18:22], "little", signed=True)),
            abs(int.from_bytes(data[22:26], "little", signed=True)))


def _tiff_size(data: bytes) -> tuple[int, int] | None:
    """Width and height (tags 256, 257) of the first image of a TIFF."""
    orders: dict[bytes, Literal["little", "big"]] = {b"II": "little", b"MM": "big"}
    order = orders.get(data[:2])
    if order is None or int.from_bytes(data[2:4], order) != 42:
        return None
    ifd = int.from_bytes(data[4:8], order)
    count = int.from_bytes(data[ifd:ifd + 2], order)
    sides: dict[int, int] = {}
    for k in range(count):
        e = ifd + 2 + 12 * k
        tag, kind = int.from_bytes(data[e:e + 2], order), int.from_bytes(data[e + 2:e + 4], order)
        if tag in (256, 257):
            sides[tag] = int.from_bytes(data[e + 8:e + (10 if kind == 3 else 12)], order)  # SHORT or LONG
    return (sides[256], sides[257]) if len(sides) == 2 else None


def _webp_size(data: bytes) -> tuple[int, int] | None:
    if data[:4] != b"RIFF" or data[8:12] != b"WEBP" or len(data) < 30:
        return None
    chunk = data[12:16]
    if chunk == b"VP8X":  # extended: canvas size minus one, 24 bits each
        return int.from_bytes(data[24:27], "little") + 1, int.from_bytes(data[27:30], "little") + 1
    if chunk == b"VP8L":  # lossless: 14 bits each, minus one
        bits = int.from_bytes(data[21:25], "little")
        return (bits & 0x3FFF) + 1, ((bits >> 14) & 0x3FFF) + 1
    if chunk == b"VP8 ":  # lossy: after the frame tag and start code
        return int.from_bytes(data[26:28], "little") & 0x3FFF, int.from_bytes(data[28:30], "little") & 0x3FFF
    return None


_STDERR_LOCK = threading.Lock()


@contextmanager
def _stderr_captured() -> Iterator[list[str]]:
    """Collect what C libraries write to file descriptor 2 meanwhile (OpenCV's codecs print their
    warnings there); the text lands in the yielded list."""
    out: list[str] = []
    with _STDERR_LOCK:
        sys.stderr.flush()
        saved = os.dup(2)
        with tempfile.TemporaryFile() as tmp:
            os.dup2(tmp.fileno(), 2)
            try:
                yield out
            finally:
                os.dup2(saved, 2)
                os.close(saved)
                tmp.seek(0)
                out.append(tmp.read().decode("utf-8", "replace"))


# What libjpeg / libpng / OpenCV's loaders print about a damaged file.
_DAMAGE = re.compile(r"(corrupt|premature end|libpng|libjpeg|invalid|crc error|truncat|not a jpeg|bogus|"
                     r"unsupported marker|huffman|extraneous bytes)", re.IGNORECASE)


def imdecode_checked(data: bytes, where: str, flags: int | None = None) -> np.ndarray:
    """cv2.imdecode (flags default IMREAD_ANYCOLOR) that refuses what OpenCV only warns about: a
    truncated or corrupt JPEG/PNG (libjpeg and libpng say so on stderr and hand back an image),
    an undecodable file, a header that claims an impossible size. FileError naming `where`; the
    codec's stderr is captured, so its warnings never reach the terminal alone."""
    import cv2
    import numpy as np

    size = image_header_size(data)
    if size is not None:
        check_image_size(size[0], size[1], where)
    with _stderr_captured() as noise:
        try:
            img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_ANYCOLOR if flags is None else flags)
        except cv2.error as e:
            if "CV_IO_MAX_IMAGE" in str(e):  # its pixel limit, which is ours: a size we refuse
                raise FileError(f"{where}: the image is larger than this program handles (at most "
                                f"{MAX_IMAGE_SIDE} per side and {MAX_IMAGE_PIXELS // 1_000_000} megapixels)") from None
            img, noise_exc = None, str(e).strip().splitlines()[-1]
        else:
            noise_exc = ""
    said = " ".join(line.strip() for line in (noise[0] if noise else "").splitlines() if line.strip())
    damage = [line.strip() for line in (noise[0] if noise else "").splitlines() if _DAMAGE.search(line)]
    kind = "PNG" if data[:8] == b"\x89PNG\r\n\x1a\n" else "JPEG" if data[:2] == b"\xff\xd8" else ""
    if kind == "JPEG" and not damage and b"\xff\xd9" not in data[-64:]:
        damage = ["no end-of-image marker: the file was cut short"]
    if img is None:
        why = damage[0] if damage else noise_exc
        if why or kind:
            raise FileError(f"{where}: truncated or corrupt {kind or 'image'}" + (f" ({why})" if why else ""))
        raise FileError(f"{where}: not an image file OpenCV can decode ({len(data)} bytes; "
                        f"known: {', '.join(IMAGE_EXTENSIONS)})")
    if damage:
        raise FileError(f"{where}: truncated or corrupt {kind or 'image'} ({damage[0]})")
    if said:  # something else the codec said: not ours to hide, not worth failing for
        print(said, file=sys.stderr)
    return img


def decode_image(data: bytes, where: str) -> np.ndarray:
    """Encoded image bytes -> (H, W) uint8 grey or (H, W, 3) uint8 BGR (alpha dropped, 16-bit
    scaled to 8). A truncated or corrupt file, an unknown format or an impossible size is a
    FileError naming `where`."""
    img = imdecode_checked(data, where)
    check_image_size(img.shape[1], img.shape[0], where)
    return img


def check_pair(left: np.ndarray, right: np.ndarray, left_name: str, right_name: str) -> None:
    """The two images of a stereo pair must agree in size and in colour (grey or BGR): else a
    FileError naming both files."""
    if left.shape != right.shape:
        def kind(a: np.ndarray) -> str:
            return f"{a.shape[1]}x{a.shape[0]} " + ("grey" if a.ndim == 2 else "colour")

        raise FileError(f"{left_name} is {kind(left)} but {right_name} is {kind(right)}: the two images of a "
                        f"stereo pair must agree in size and colour")


def read_image(path: str | Path, what: str = "") -> np.ndarray:
    """One image file -> (H, W) uint8 grey or (H, W, 3) uint8 BGR; FileError on any problem."""
    data = read_bytes(path, what)
    return decode_image(data, f"{what} {path}" if what else str(path))


# --- lists of image files ------------------------------------------------------------------------

def list_images(spec: str, what: str) -> list[Path]:
    """A folder (every image file in it), a glob pattern ('left/*.png', 'data/**/im0.png') or one
    file -> image files in natural order (img2 before img10). `what` names the argument in errors
    (e.g. "LEFT" or "--images-left")."""
    if not spec:
        raise FileError(f"{what}: no folder, pattern or file given")
    path = Path(os.path.expanduser(spec))
    if path.is_dir():
        files = [f for f in path.iterdir() if f.suffix.lower() in IMAGE_EXTENSIONS and f.is_file()]
        if not files:
            raise FileError(f"{what} {spec}: the folder holds no image files ({', '.join(IMAGE_EXTENSIONS)})")
    elif path.is_file():
        files = [path]
    else:
        files = [Path(f) for f in glob.glob(os.path.expanduser(spec), recursive=True)
                 if Path(f).is_file() and Path(f).suffix.lower() in IMAGE_EXTENSIONS]
        if not files:
            why = "no file matches the pattern" if glob.has_magic(spec) else "no such file or folder"
            raise FileError(f"{what} {spec}: {why}")
    return natural_sorted(files)


_SIDE = re.compile(r"(left|right|links|rechts)", re.IGNORECASE)


def _pair_key(path: Path) -> str:
    return _SIDE.sub("#", path.stem).lower()


def pair_images(left: Sequence[Path], right: Sequence[Path]) -> list[tuple[Path, Path]]:
    """Left and right files paired by name (the name with left/right removed: left03.png and
    right03.png), else, with equal counts, in natural order. Different counts are a FileError that
    names files without a partner."""
    lk = {_pair_key(p): p for p in left}
    rk = {_pair_key(p): p for p in right}
    if len(lk) == len(left) and len(rk) == len(right) and set(lk) == set(rk):
        return [(lk[k], rk[k]) for k in natural_sorted(list(lk))]
    if len(left) != len(right):
        only_l = natural_sorted(list(set(lk) - set(rk)))
        only_r = natural_sorted(list(set(rk) - set(lk)))
        detail = ""
        if only_l or only_r:
            unpaired = [str(lk[k]) for k in only_l[:5]] + [str(rk[k]) for k in only_r[:5]]
            detail = "; without a partner: " + ", ".join(unpaired)
        raise FileError(f"{len(left)} left images but {len(right)} right images{detail}")
    return list(zip(natural_sorted(list(left)), natural_sorted(list(right))))

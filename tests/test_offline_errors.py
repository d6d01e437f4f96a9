"""Every offline command turns a bad file into one line on stderr and exit status 2, names the file
and writes nothing: 1x1 or huge images, empty, binary, truncated or corrupt JPEG/PNG, missing
files, binary or empty calibration files and calibrations of impossible size. OpenCV's own warnings
(libjpeg's "Corrupt JPEG data", libpng's "IDAT: CRC error") never reach the terminal by themselves.
Plus natural sort of offline file lists and one flag name per concept across commands."""
from __future__ import annotations

import json
import os
import re
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest

from ballbot_vision.cli import main

W, H = 320, 240


def _scene() -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(1)
    left = cv2.GaussianBlur(rng.integers(0, 255, (H, W), np.uint8), (3, 3), 0)
    right = np.roll(left, -8, axis=1)
    return left, right


def _png_header_only(w: int, h: int) -> bytes:
    """A PNG whose header claims w x h (a decompression bomb in miniature): signature + IHDR."""
    ihdr = w.to_bytes(4, "big") + h.to_bytes(4, "big") + bytes([8, 0, 0, 0, 0])
    chunk = b"IHDR" + ihdr
    return b"\x89PNG\r\n\x1a\n" + len(ihdr).to_bytes(4, "big") + chunk + zlib.crc32(chunk).to_bytes(4, "big")


def _bmp_header_only(w: int, h: int) -> bytes:
    """A BMP whose BITMAPINFOHEADER claims w x h, 24 bit, followed by a few bytes of pixels."""
    info = (40).to_bytes(4, "little") + w.to_bytes(4, "little") + h.to_bytes(4, "little", signed=True) \
        + (1).to_bytes(2, "little") + (24).to_bytes(2, "little") + bytes(24)
    return b"BM" + (54 + 64).to_bytes(4, "little") + bytes(4) + (54).to_bytes(4, "little") + info + bytes(64)


def _jpeg(img: np.ndarray) -> bytes:
    return cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 95])[1].tobytes()


def _bad_images() -> dict[str, tuple[str, bytes, str]]:
    """name -> (file suffix, content, expected phrase)."""
    left, _ = _scene()
    jpg, png = _jpeg(left), cv2.imencode(".png", left)[1].tobytes()
    corrupt = bytearray(jpg)
    corrupt[len(jpg) // 2:len(jpg) // 2 + 64] = b"\x00" * 64
    crc = bytearray(png)
    crc[len(png) // 2] ^= 0xFF
    return {
        "1x1": (".png", cv2.imencode(".png", np.zeros((1, 1), np.uint8))[1].tobytes(), "1x1 pixels is too small"),
        "huge-header": (".png", _png_header_only(100000, 100000), "100000x100000 pixels is larger than"),
        "huge-pgm-header": (".pgm", b"P5\n# a comment\n30000 30000\n255\n" + bytes(100),
                            "30000x30000 pixels is larger than"),
        "huge-bmp-header": (".bmp", _bmp_header_only(50000, -50000), "50000x50000 pixels is larger than"),
        "empty": (".png", b"", "the file is empty"),
        "binary": (".png", bytes(range(256)) * 8, "not an image file OpenCV can decode"),
        "truncated-jpeg": (".jpg", jpg[:len(jpg) // 2], "truncated or corrupt JPEG"),
        "corrupt-jpeg": (".jpg", bytes(corrupt), "truncated or corrupt JPEG"),
        "truncated-png": (".png", png[:len(png) // 2], "truncated or corrupt PNG"),
        "crc-png": (".png", bytes(crc), "truncated or corrupt PNG"),
    }


BAD_IMAGES = _bad_images()


def _commands(left: Path, right: Path, out: Path) -> dict[str, list[str]]:
    return {
        "rectify": ["rectify", str(left), str(right), "--calibration", "lifecam-studio", "-o", str(out)],
        "disparity": ["disparity", str(left), str(right), "-o", str(out / "d.npy")],
        "obstacles": ["obstacles", str(left), str(right), "--calibration", "lifecam-studio"],
        "calibration check": ["calibration", "check", str(left), str(right), "--calibration", "lifecam-studio"],
        "calibrate": ["calibrate", "--left", str(left), "--right", str(right), "--square-size", "0.03",
                      "-o", str(out / "rig.yaml")],
    }


def _one_line_error(capfd, rc: int, *needles: str) -> str:
    captured = capfd.readouterr()
    err = captured.err
    assert rc == 2, (rc, err)
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("ballbot-vision: error: "), err
    for n in needles:
        assert n in err, (n, err)
    assert "Traceback" not in err and "Corrupt JPEG" not in captured.out
    return err


@pytest.mark.parametrize("command", ["rectify", "disparity", "obstacles", "calibration check", "calibrate"])
@pytest.mark.parametrize("bad", list(BAD_IMAGES))
def test_bad_image_files_are_one_line_errors(tmp_path, capfd, command, bad):
    suffix, content, phrase = BAD_IMAGES[bad]
    left, right = _scene()
    good = tmp_path / f"right{suffix}"
    cv2.imwrite(str(good), right)
    bad_file = tmp_path / f"left{suffix}"
    bad_file.write_bytes(content)
    out = tmp_path / "out"
    rc = main(_commands(bad_file, good, out)[command])
    _one_line_error(capfd, rc, str(bad_file), phrase)
    assert not (out / "d.npy").exists() and not (out / "rig.yaml").exists()
    assert not out.exists() or not any(out.rglob("*.png"))


@pytest.mark.parametrize("command", ["rectify", "disparity", "obstacles", "calibration check"])
def test_missing_image_file(tmp_path, capfd, command):
    left, right = _scene()
    cv2.imwrite(str(tmp_path / "right.png"), right)
    rc = main(_commands(tmp_path / "nope.png", tmp_path / "right.png", tmp_path / "out")[command])
    err = _one_line_error(capfd, rc, "nope.png")
    assert "no such file" in err


def test_a_real_image_above_the_pixel_limit_is_refused(tmp_path, capfd):
    big = np.zeros((6000, 8000), np.uint8)  # 48 MP: over the 40 MP limit, a small PNG on disk
    cv2.imwrite(str(tmp_path / "l.png"), big)
    cv2.imwrite(str(tmp_path / "r.png"), big)
    rc = main(["disparity", str(tmp_path / "l.png"), str(tmp_path / "r.png"), "-o", str(tmp_path / "d.npy")])
    _one_line_error(capfd, rc, "8000x6000 pixels is larger than", "l.png")
    assert not (tmp_path / "d.npy").exists()


@pytest.mark.parametrize("content,phrase", [
    (b"", "the file is empty"),
    (bytes(range(256)) * 4, "binary data, not a text file"),
    (b"rectified: true\nimage_size: [200000, 200000]\nfocal_px: 700\nprincipal_point: [1, 1]\nbaseline_m: 0.1\n",
     "200000x200000 pixels is larger than"),
    (b"name: x\nrectified: false\nimage_size: [320, 240]\nleft: {K: [.nan, 0, 160, 0, 500, 120, 0, 0, 1], "
     b"distortion: [0, 0, 0, 0, 0]}\n", "finite numbers"),
])
@pytest.mark.parametrize("command", ["rectify", "disparity", "obstacles", "calibration check", "calibration show"])
def test_bad_calibration_files_are_one_line_errors(tmp_path, capfd, command, content, phrase):
    left, right = _scene()
    cv2.imwrite(str(tmp_path / "left.png"), left)
    cv2.imwrite(str(tmp_path / "right.png"), right)
    cal = tmp_path / "cal.yaml"
    cal.write_bytes(content)
    argv = _commands(tmp_path / "left.png", tmp_path / "right.png", tmp_path / "out").get(command)
    if command == "calibration show":
        argv = ["calibration", "show", str(cal)]
    elif command == "disparity":
        argv = argv + ["--calibration", str(cal)]
    else:
        argv = [a if a != "lifecam-studio" else str(cal) for a in argv]
    rc = main(argv)
    _one_line_error(capfd, rc, str(cal), phrase)
    assert not (tmp_path / "out" / "d.npy").exists()


@pytest.mark.parametrize("ext,params", [(".png", []), (".jpg", []), (".pgm", []), (".ppm", []), (".bmp", []),
                                        (".tif", []), (".tif", [cv2.IMWRITE_TIFF_COMPRESSION, 1]), (".webp", []),
                                        (".webp", [cv2.IMWRITE_WEBP_QUALITY, 101])])
def test_image_sizes_are_read_from_every_header_opencv_writes(ext, params):
    from common.files import image_header_size

    img = np.zeros((37, 53, 3) if ext == ".ppm" else (37, 53), np.uint8)
    assert image_header_size(cv2.imencode(ext, img, params)[1].tobytes()) == (53, 37)


def test_an_oversized_image_of_a_format_without_a_known_header_is_refused_by_opencv_before_decoding(tmp_path):
    """OpenCV's own size limits are set to ours before cv2 loads (ballbot_vision/__init__.py): a
    format image_header_size does not read (Sun raster) is held to them too, before OpenCV
    allocates the image. With OpenCV's default limit (1 gigapixel) this 48 MP header cut off from
    its pixels was "not an image file"."""
    import subprocess
    import sys

    ras = bytes.fromhex("59a66a95") + b"".join(v.to_bytes(4, "big") for v in (8000, 6000, 8, 48_000_000, 1, 0, 0))
    (tmp_path / "l.ras").write_bytes(ras + bytes(100))
    cv2.imwrite(str(tmp_path / "r.png"), _scene()[1])
    env = {k: v for k, v in os.environ.items() if not k.startswith("OPENCV_IO_MAX_IMAGE")}
    r = subprocess.run([sys.executable, "-m", "ballbot_vision.cli", "disparity", str(tmp_path / "l.ras"),
                        str(tmp_path / "r.png"), "-o", str(tmp_path / "d.npy")], capture_output=True, text=True,
                       timeout=120, env=env)
    assert r.returncode == 2 and r.stderr.count("\n") == 1, r.stderr
    assert f"LEFT {tmp_path / 'l.ras'}: the image is larger than this program handles" in r.stderr


def test_offline_file_lists_sort_naturally(tmp_path, capfd):
    """left2 before left10: a sequence is tracked in the order it was recorded."""
    left, right = (cv2.resize(i, (640, 480)) for i in _scene())
    (tmp_path / "L").mkdir(), (tmp_path / "R").mkdir()
    for i in (1, 2, 10, 11):
        cv2.imwrite(str(tmp_path / "L" / f"left{i}.png"), left)
        cv2.imwrite(str(tmp_path / "R" / f"right{i}.png"), right)
    out = tmp_path / "out"
    assert main(["rectify", str(tmp_path / "L"), str(tmp_path / "R"), "--calibration", "lifecam-studio",
                 "-o", str(out)]) == 0
    lines = [ln for ln in capfd.readouterr().out.splitlines() if " -> " in ln]
    assert [Path(ln.split()[0]).name for ln in lines] == ["left1.png", "left2.png", "left10.png", "left11.png"]
    assert main(["obstacles", str(tmp_path / "L"), str(tmp_path / "R"), "--calibration", "lifecam-studio",
                 "--json"]) == 0
    docs = [json.loads(ln) for ln in capfd.readouterr().out.splitlines()]
    assert [Path(d["left"]).name for d in docs] == ["left1.png", "left2.png", "left10.png", "left11.png"]
    assert [d["seq"] for d in docs] == [0, 1, 2, 3]


def test_one_flag_name_per_concept(capfd):
    """The disparity method is --method in `disparity`, --disparity-method where a command also has
    the segmenter's --method; offline `disparity` shows no worker-pool flags."""
    import argparse

    from ballbot_vision.cli import build_parser

    def help_of(*argv: str) -> str:
        p = build_parser(list(argv))
        sub = next(a for a in p._actions if isinstance(a, argparse._SubParsersAction))
        sp = sub.choices[argv[0]]
        if len(argv) > 1:
            sp = next(a for a in sp._actions if isinstance(a, argparse._SubParsersAction)).choices[argv[1]]
        return sp.format_help()

    disparity, obstacles, evaluation = help_of("disparity"), help_of("obstacles"), help_of("eval")
    run_disparity = help_of("run", "disparity")
    assert "--method" in disparity and "--matcher" not in disparity
    for text in (obstacles, evaluation):
        assert "--disparity-method" in text and "--disparity-num-disparities" in text and "--matcher" not in text
    for flag in ("--max-in-flight", "--result-timeout-s", "--role", "--fallback"):
        assert flag in run_disparity and flag not in disparity and flag not in obstacles


def test_an_image_of_another_size_than_the_calibration_names_the_file(tmp_path, capfd):
    left, right = _scene()
    cv2.imwrite(str(tmp_path / "l.png"), left)
    cv2.imwrite(str(tmp_path / "r.png"), right)
    for argv in (["rectify", "-o", str(tmp_path / "out")], ["obstacles"], ["calibration", "check"],
                 ["disparity", "-o", str(tmp_path / "d.npy")]):
        rc = main(argv[:2 if argv[0] == "calibration" else 1] + [str(tmp_path / "l.png"), str(tmp_path / "r.png"),
                  "--calibration", "lifecam-studio"] + argv[2 if argv[0] == "calibration" else 1:])
        _one_line_error(capfd, rc, f"{tmp_path / 'l.png'}: image is 320x240", "640x480")


def test_a_missing_path_reads_the_same_in_every_command(tmp_path, capfd):
    """One wording for "nothing there": `<argument> <path>: no such file or folder`."""
    left, right = _scene()
    cv2.imwrite(str(tmp_path / "right.png"), right)
    nope, out = tmp_path / "nope.png", tmp_path / "out"
    cases = {**{name: (argv, "LEFT") for name, argv in _commands(nope, tmp_path / "right.png", out).items()},
             "mcap from-images": (["mcap", "from-images", str(nope), str(tmp_path / "right.png"), "-o",
                                   str(out / "x.mcap")], "LEFT"),
             "calibration show": (["calibration", "show", str(nope)], "calibration"),
             "calibration import": (["calibration", "import", str(nope), "-o", str(out / "i.yaml")], ""),
             "mcap info": (["mcap", "info", str(nope)], "recording"),
             "calibrate --pairs": (["calibrate", "--pairs", str(nope), "--square-size", "0.03"], "--pairs"),
             "sample-pair --scenario": (["sample-pair", str(out / "s"), "--scenario", str(nope)], "scenario"),
             "--config": (["obstacles", str(nope), str(nope), "--calibration", "lifecam-studio", "--config",
                           str(nope)], "config")}
    cases["calibrate"] = (cases["calibrate"][0], "--left")
    for name, (argv, what) in cases.items():
        rc = main(argv)
        err = _one_line_error(capfd, rc)
        assert f"error: {what + ' ' if what else ''}{nope}: no such file or folder" in err, (name, err)


def test_an_output_path_that_cannot_be_written_is_a_one_line_error(tmp_path, capfd):
    """-o into a file, or a folder where a file goes: the path and the reason, exit 2, no traceback."""
    left, right = _scene()
    cv2.imwrite(str(tmp_path / "l.png"), left)
    cv2.imwrite(str(tmp_path / "r.png"), right)
    (tmp_path / "a-file").write_text("x")
    (tmp_path / "a-folder").mkdir()
    (tmp_path / "taken.png").mkdir()  # an image's name held by a folder: OpenCV's imwrite only says False
    l, r, f = str(tmp_path / "l.png"), str(tmp_path / "r.png"), tmp_path / "a-file"
    for argv, where, why in [
        (["disparity", l, r, "--num-disparities", "64", "-o", str(tmp_path / "taken.png")], tmp_path / "taken.png",
         "cannot write the image"),
        (["disparity", l, r, "--num-disparities", "64", "-o", f"{f}/d.npy"], f, "is a file, not a folder"),
        (["rectify", l, r, "--calibration", "lifecam-studio", "-o", str(f)], f, "is a file, not a folder"),
        (["calibration", "show", "lifecam-studio"], None, None),
        (["calibration", "export", "lifecam-studio", f"{f}/l.yaml", f"{f}/r.yaml"], f"{f}/l.yaml",
         "a part of the path is a file, not a folder"),
        (["sample-pair", str(f)], f, "is a file, not a folder"),
        (["mcap", "from-images", l, r, "-o", f"{f}/x.mcap"], f"{f}/x.mcap", "a part of the path is a file"),
    ]:
        rc = main(argv)
        if where is None:
            assert rc == 0
            capfd.readouterr()
            continue
        _one_line_error(capfd, rc, f"{where}: ", why)
    # a calibration written over a folder: refused before anything is written
    rc = main(["calibration", "export", "lifecam-studio", str(tmp_path / "a-folder"), str(tmp_path / "r.yaml"),
               "--format", "ros"])
    _one_line_error(capfd, rc, f"{tmp_path / 'a-folder'}: is a folder, not a file")


def test_a_bad_image_in_the_middle_of_a_conversion_keeps_the_pairs_before_it(tmp_path, capfd):
    pytest.importorskip("mcap")
    from cores.recording_reader import RecordingReader

    left, right = _scene()
    (tmp_path / "L").mkdir(), (tmp_path / "R").mkdir()
    for i in (1, 2, 3, 10):
        cv2.imwrite(str(tmp_path / "L" / f"left{i}.png"), left)
        cv2.imwrite(str(tmp_path / "R" / f"right{i}.png"), right)
    (tmp_path / "L" / "left10.png").write_bytes(BAD_IMAGES["truncated-png"][1])
    out = tmp_path / "x.mcap"
    rc = main(["mcap", "from-images", str(tmp_path / "L"), str(tmp_path / "R"), "-o", str(out)])
    _one_line_error(capfd, rc, "left10.png: truncated or corrupt PNG", f"{out} holds the 3 pair(s) before it")
    assert len(list(RecordingReader(out).pairs())) == 3


def test_a_bad_pair_in_a_folder_costs_that_pair_and_obstacles_go_on(tmp_path, capfd):
    """A truncated image in the middle of a folder: `obstacles` names it, skips its pair and goes on with
    the rest (it used to stop there, and the pairs after it were never looked at), as it does in a
    recording; a folder with nothing readable is the one-line error."""
    left, right = (cv2.resize(i, (640, 480)) for i in _scene())  # the calibration's size
    (tmp_path / "L").mkdir(), (tmp_path / "R").mkdir()
    for i in (1, 2, 3):
        cv2.imwrite(str(tmp_path / "L" / f"left{i}.png"), left)
        cv2.imwrite(str(tmp_path / "R" / f"right{i}.png"), right)
    (tmp_path / "L" / "left2.png").write_bytes(BAD_IMAGES["truncated-png"][1])
    argv = ["obstacles", str(tmp_path / "L"), str(tmp_path / "R"), "--calibration", "lifecam-studio", "--json"]
    capfd.readouterr()
    assert main(argv) == 0
    out, err = capfd.readouterr()
    lists = [json.loads(line) for line in out.splitlines()]
    assert [Path(doc["left"]).name for doc in lists] == ["left1.png", "left3.png"]
    assert [doc["seq"] for doc in lists] == [0, 2]  # each list's seq is its pair's place: the skipped one's left out
    (said,) = [line for line in err.splitlines() if "pair skipped" in line]
    assert said.startswith(f"ballbot-vision: warning: {tmp_path / 'L' / 'left2.png'}: truncated or corrupt PNG"), err
    assert "1 of 3 pair(s) could not be read" in err and "Traceback" not in err
    for i in (1, 3):
        (tmp_path / "L" / f"left{i}.png").write_bytes(BAD_IMAGES["truncated-png"][1])
    assert main(argv) == 2
    out, err = capfd.readouterr()
    assert out == "" and err.count("pair skipped") == 3, err
    assert err.strip().splitlines()[-1] == "ballbot-vision: error: obstacles: none of the 3 pairs could be read " \
                                           "(named above)", err


def test_a_grey_and_a_colour_image_are_not_a_pair(tmp_path, capfd):
    left, right = _scene()
    cv2.imwrite(str(tmp_path / "l.png"), left)
    cv2.imwrite(str(tmp_path / "r.png"), cv2.cvtColor(right, cv2.COLOR_GRAY2BGR))
    for argv in (["disparity", "-o", str(tmp_path / "d.npy")],
                 ["obstacles", "--calibration", str(tmp_path / "cal.yaml")]):
        (tmp_path / "cal.yaml").write_text("rectified: true\nimage_size: [320, 240]\nfocal_px: 300\n"
                                           "principal_point: [160, 120]\nbaseline_m: 0.1\n")
        rc = main(argv[:1] + [str(tmp_path / "l.png"), str(tmp_path / "r.png")] + argv[1:])
        _one_line_error(capfd, rc, "l.png is 320x240 grey but ", "r.png is 320x240 colour")
    assert not (tmp_path / "d.npy").exists()


def _laughs(levels: int = 9) -> str:
    """A few hundred bytes of nested YAML aliases ("billion laughs") that expand to 9**levels values."""
    lines = ['l0: &l0 ["x", "x", "x", "x", "x", "x", "x", "x", "x"]']
    lines += [f"l{i}: &l{i} [{', '.join([f'*l{i - 1}'] * 9)}]" for i in range(1, levels)]
    return "\n".join(lines) + f"\nrectified: true\nfocal_px: 700\nprincipal_point: [1, 1]\nbaseline_m: 0.1\n" \
                              f"image_size: *l{levels - 1}\n"


HOSTILE_YAML = {
    "aliases": (_laughs(), "YAML aliases that expand to more than 200000 values"),
    "self-reference": ("a: &a [*a]\n", "YAML aliases that expand to more than 200000 values (endless)"),
    "nesting": ("a: " + "[" * 5000 + "]" * 5000 + "\n", "YAML nested too deeply"),
}


@pytest.mark.parametrize("kind", list(HOSTILE_YAML))
@pytest.mark.parametrize("command", ["calibration show", "calibration import", "obstacles", "--config"])
def test_hostile_yaml_is_refused_before_it_is_walked(tmp_path, capfd, command, kind):
    """A 700-byte calibration of nested aliases took 1.6 GB and 4 s before it was refused; deep
    nesting was a RecursionError traceback."""
    text, phrase = HOSTILE_YAML[kind]
    bad = tmp_path / "bad.yaml"
    bad.write_text(text)
    left, right = _scene()
    cv2.imwrite(str(tmp_path / "l.png"), left)
    cv2.imwrite(str(tmp_path / "r.png"), right)
    argv = {"calibration show": ["calibration", "show", str(bad)],
            "calibration import": ["calibration", "import", str(bad), "-o", str(tmp_path / "i.yaml")],
            "obstacles": ["obstacles", str(tmp_path / "l.png"), str(tmp_path / "r.png"), "--calibration", str(bad)],
            "--config": ["obstacles", str(tmp_path / "l.png"), str(tmp_path / "r.png"), "--calibration",
                         "lifecam-studio", "--config", str(bad)]}[command]
    rc = main(argv)
    _one_line_error(capfd, rc, str(bad), phrase)
    assert not (tmp_path / "i.yaml").exists()


def test_a_hostile_calibration_message_is_refused_by_rectify():
    """The same YAML on the calibration key: refused and logged, the calibration in use stays."""
    from cores.calibration.rectify import CalibrationHolder

    holder = CalibrationHolder("lifecam-studio")
    before = holder.current()
    assert not holder.offer_yaml(HOSTILE_YAML["aliases"][0], "a message")
    assert holder.current() is before and "expand to more than 200000 values" in holder.last_error


@pytest.mark.parametrize("content,phrase", [
    ("M1: !!opencv-matrix\n   rows: 3\n   cols: 3\n", "field 'M1' is not a readable OpenCV matrix: no 'dt'"),
    ("M1: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n   data: [ 1, 2 ]\n",
     "field 'M1' is not a readable OpenCV matrix: its 'data' do not hold rows x cols numbers"),
    ("image_width: .nan\nimage_height: 480\n", "field 'image_width' must be a whole number of pixels, got nan"),
])
def test_an_opencv_file_with_broken_fields_is_a_one_line_error(tmp_path, capfd, content, phrase):
    """cv::FileStorage's own assertions (cv2.error) and a NaN size were tracebacks."""
    from cores import camera

    rig = camera.load_calibration("lifecam-studio")
    mat = lambda m: "!!opencv-matrix\n   rows: {}\n   cols: {}\n   dt: d\n   data: [ {} ]\n".format(  # noqa: E731
        *np.atleast_2d(m).shape, ", ".join(f"{v:.6f}" for v in np.ravel(m)))
    good = {"M1": rig.left.K, "D1": rig.left.D[None], "M2": rig.right.K, "D2": rig.right.D[None]}
    key = content.split(":", 1)[0]
    body = "".join(f"{k}: {mat(v)}" for k, v in good.items() if k != key)
    (tmp_path / "intrinsics.yml").write_text("%YAML:1.0\n" + content + body)
    (tmp_path / "extrinsics.yml").write_text("%YAML:1.0\n" + f"R: {mat(rig.R)}T: {mat(rig.T[:, None] * 1000)}")
    argv = ["calibration", "import", str(tmp_path / "intrinsics.yml"), str(tmp_path / "extrinsics.yml"),
            "--units-m", "0.001", "-o", str(tmp_path / "rig.yaml")]
    size = [] if key == "image_width" else ["--image-size", "640x480"]  # else the file gives it
    rc = main(argv + size)
    _one_line_error(capfd, rc, str(tmp_path / "intrinsics.yml"), phrase)
    assert not (tmp_path / "rig.yaml").exists()
    # the same files, repaired, import
    (tmp_path / "intrinsics.yml").write_text("%YAML:1.0\n" + "".join(f"{k}: {mat(v)}" for k, v in good.items()))
    assert main(argv + ["--image-size", "640x480"]) == 0
    assert camera.load_calibration(str(tmp_path / "rig.yaml")).image_size == (640, 480)


def test_a_damaged_jpeg_inside_a_recording_is_skipped_with_its_reason(tmp_path, capfd, caplog):
    """libjpeg only warns about a damaged JPEG and hands back a grey-smeared image: inside a
    recording the pair is skipped and named (it used to yield obstacles, exit 0, with "Corrupt
    JPEG data" alone on stderr); the pairs around it go on."""
    pytest.importorskip("mcap")
    left, right = (cv2.resize(i, (640, 480)) for i in _scene())
    (tmp_path / "L").mkdir(), (tmp_path / "R").mkdir()
    for i in range(3):
        cv2.imwrite(str(tmp_path / "L" / f"left{i}.png"), left)
        cv2.imwrite(str(tmp_path / "R" / f"right{i}.png"), right)
    rec = tmp_path / "rec.mcap"
    assert main(["mcap", "from-images", str(tmp_path / "L"), str(tmp_path / "R"), "-o", str(rec), "--format", "jpeg",
                 "--compression", "none", "--calibration", "lifecam-studio"]) == 0
    data = bytearray(rec.read_bytes())
    starts = [m.start() for m in re.finditer(rb"\xff\xd8\xff", data)]  # each JPEG's first bytes (binary payloads)
    assert len(starts) == 6
    middle = starts[2] + (data.index(b"\xff\xd9", starts[2]) - starts[2]) // 2  # pair 1's left image, mid-scan
    data[middle:middle + 2000] = bytes(2000)  # the message keeps its length: zeros inside the JPEG
    rec.write_bytes(bytes(data))
    capfd.readouterr()

    assert main(["obstacles", str(rec), "--json", "--disparity-num-disparities", "32"]) == 0
    out, err = capfd.readouterr()
    lists = [json.loads(line) for line in out.splitlines()]
    assert [doc["left"] for doc in lists] == [f"{rec}#0:left", f"{rec}#2:left"]
    assert [doc["seq"] for doc in lists] == [0, 2]
    said = err + caplog.text  # the warning is logged (pytest's handler holds it in-process)
    assert "pair seq 1 left: truncated or corrupt JPEG" in said and "pair skipped" in said
    assert not any(line.startswith("Corrupt JPEG") for line in err.splitlines()), err

    assert main(["mcap", "to-images", str(rec), "-o", str(tmp_path / "out")]) == 0
    err = capfd.readouterr().err
    assert "wrote 2 raw pairs" in err and "1 pair(s) with a damaged image skipped" in err

"""Settings from flags and the environment are parsed by the field's type (pydantic's coercion), not
guessed as YAML; errors name where a value came from; the commands that containers run first
(`run router`, `healthcheck`) import neither OpenCV nor any service."""
from __future__ import annotations

import argparse
import subprocess
import sys

import pytest

from ballbot_vision.cli import build_parser
from common.errors import ConfigError
from common.settings import MountSettings, add_settings_arguments, load_settings
from cores.segmentation.settings import SegmenterSettings
from services.capture.settings import CaptureSettings


def capture(argv: list[str], config: str | None = None) -> CaptureSettings:
    args = build_parser(["run", "capture", *argv]).parse_args(["run", "capture", *argv])
    return load_settings(CaptureSettings, config, args)


def test_a_device_number_with_a_leading_zero_is_decimal_not_octal():
    assert capture(["--camera-left", "010"]).camera_left == 10  # YAML read this as 8
    assert capture(["--camera-left", "/dev/v4l/by-id/usb-cam-index0"]).camera_left == "/dev/v4l/by-id/usb-cam-index0"
    assert capture(["--sbs-device", "3"]).sbs_device == 3


def test_text_fields_stay_text_whatever_yaml_would_make_of_them():
    s = capture(["--scenario", "yes", "--calibration", "1.0", "--images-left", "0x10", "--video-left", "null"])
    assert (s.scenario, s.calibration, s.images_left, s.video_left) == ("yes", "1.0", "0x10", "null")


def test_numbers_bools_and_unset_by_type(monkeypatch):
    s = capture(["--rate-hz", "15", "--loop", "--grayscale", "no", "--camera-exposure", "null"])
    assert s.rate_hz == 15.0 and s.loop is True and s.grayscale is False and s.camera_exposure is None
    monkeypatch.setenv("BALLBOT_CAPTURE_CAMERA_EXPOSURE", "250")
    monkeypatch.setenv("BALLBOT_CAPTURE_CAMERA_RIGHT", "012")
    s = capture([])
    assert s.camera_exposure == 250.0 and s.camera_right == 12
    assert capture(["--camera-exposure", "None"]).camera_exposure is None  # the flag beats the environment


def test_numeric_choices_and_optional_numbers():
    p = argparse.ArgumentParser()
    add_settings_arguments(p, SegmenterSettings)
    add_settings_arguments(p, MountSettings, prefix="mount-")
    args = p.parse_args(["--median-ksize", "3", "--max-range-m", "none", "--mount-height-m", "0.8"])
    s = load_settings(SegmenterSettings, None, args)
    assert s.median_ksize == 3 and s.max_range_m is None
    assert load_settings(MountSettings, None, args, prefix="mount-").height_m == 0.8


@pytest.mark.parametrize("argv,where,what", [
    (["--rate-hz", "fast"], "--rate-hz", "'fast'"),
    (["--camera-width", "640px"], "--camera-width", "'640px'"),
    (["--loop", "maybe"], "--loop", "'maybe'"),
    (["--source", "webcam"], "--source", "'webcam'"),
    (["--rate-hz", "-1"], "--rate-hz", "greater than 0"),
    (["--jpeg-quality", "null"], "--jpeg-quality", "'null'"),  # not optional: null is no number
])
def test_a_bad_flag_is_named_with_its_value(argv, where, what):
    with pytest.raises(ConfigError) as e:
        capture(argv)
    assert where in str(e.value) and what in str(e.value), str(e.value)


def test_env_and_config_file_are_named_too(tmp_path, monkeypatch):
    monkeypatch.setenv("BALLBOT_CAPTURE_RATE_HZ", "often")
    with pytest.raises(ConfigError, match="environment variable BALLBOT_CAPTURE_RATE_HZ: .*'often'"):
        capture([])
    monkeypatch.delenv("BALLBOT_CAPTURE_RATE_HZ")
    cfg = tmp_path / "c.yaml"
    cfg.write_text("capture: {rate_hz: 0}\n")
    with pytest.raises(ConfigError, match=f"{cfg}: capture.rate_hz: .*greater than 0"):
        capture([], str(cfg))
    cfg.write_bytes(b"\x89PNG\r\n\x1a\n\x00\x00\xff\xfe")
    with pytest.raises(ConfigError, match=f"config {cfg}: binary data, not a text file"):
        capture([], str(cfg))
    with pytest.raises(ConfigError, match=f"config {tmp_path / 'missing.yaml'}: no such file or folder"):
        capture([], str(tmp_path / "missing.yaml"))
    cfg.write_text("")  # an empty config is no settings, not an error
    assert capture([], str(cfg)).rate_hz == capture([]).rate_hz


def test_a_misspelled_config_section_is_an_error_naming_the_known_ones(tmp_path):
    """`captur:` used to be ignored in silence: the pipeline ran on the defaults."""
    cfg = tmp_path / "c.yaml"
    cfg.write_text("captur: {rate_hz: 15}\nrectify: {}\nsegmentr: {}\nnonsense: 1\n")
    with pytest.raises(ConfigError) as e:
        capture([], str(cfg))
    msg = str(e.value)
    assert (f"{cfg}: unknown sections 'captur' (did you mean 'capture'?), 'segmentr' (did you mean 'segmenter'?), "
            f"'nonsense'; the known sections are capture, rectify, ") in msg, msg
    r = subprocess.run([sys.executable, "-m", "ballbot_vision.cli", "obstacles", "a.png", "b.png",
                        "--config", str(cfg)], capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "unknown sections 'captur'" in r.stderr and "Traceback" not in r.stderr, r.stderr
    cfg.write_text("capture: {rate_hz: 15}\nmount: {}\nforxglove: {}\n")
    with pytest.raises(ConfigError, match=r"unknown section 'forxglove' \(did you mean 'foxglove'\?\)"):
        capture([], str(cfg))


def test_every_settings_section_is_a_known_one():
    """The known sections are the settings models' own (and the shared `mount:`)."""
    import importlib

    from common.settings import KNOWN_SECTIONS, ServiceSettings
    from common.supervisor import SERVICES

    for module, _ in SERVICES.values():
        importlib.import_module(module)
    importlib.import_module("services.recorder.main")

    def subclasses(cls):
        for c in cls.__subclasses__():
            yield c
            yield from subclasses(c)

    sections = {c.section for c in subclasses(ServiceSettings) if c.section and c.__module__.split(".")[0] != "tests"
                and not c.__module__.startswith("test_")}
    assert sections and sections <= set(KNOWN_SECTIONS), sections - set(KNOWN_SECTIONS)
    assert set(KNOWN_SECTIONS) - sections <= {"mount"}


def test_several_stages_in_one_command_keep_their_values_apart():
    """A command that runs two stages names the other stage's settings with its prefix; the
    values of equal field names never mix."""
    from common.settings import ServiceSettings

    class Other(ServiceSettings):
        section = "other"
        method: str = "a"
        max_range_m: float = 1.0

    p = argparse.ArgumentParser()
    add_settings_arguments(p, SegmenterSettings)
    add_settings_arguments(p, Other, prefix="other-")
    args = p.parse_args(["--method", "seed", "--other-method", "b", "--other-max-range-m", "2.5"])
    assert load_settings(SegmenterSettings, None, args).method == "seed"
    assert load_settings(SegmenterSettings, None, args).max_range_m is None
    o = load_settings(Other, None, args, prefix="other-")
    assert (o.method, o.max_range_m) == ("b", 2.5)
    with pytest.raises(ConfigError, match="--other-max-range-m"):
        load_settings(Other, None, p.parse_args(["--other-max-range-m", "far"]), prefix="other-")


@pytest.mark.parametrize("argv", [["run", "router", "--help"], ["healthcheck", "--help"],
                                  ["--log-level", "DEBUG", "run", "router", "--help"], ["keys"], ["schema"]])
def test_router_and_healthcheck_import_neither_opencv_numpy_nor_any_service(argv):
    code = ("import sys\nfrom ballbot_vision import cli\n"
            "try:\n    cli.main(sys.argv[1:])\nexcept SystemExit:\n    pass\n"
            "heavy = sorted(m for m in sys.modules if m in ('cv2', 'scipy', 'numpy')"
            " or m.startswith(('services', 'bench')))\n"
            "print('HEAVY', heavy, file=sys.stderr)\n")
    r = subprocess.run([sys.executable, "-c", code, *argv], capture_output=True, text=True, timeout=120)
    assert "HEAVY []" in r.stderr, r.stderr[-2000:]


def test_run_service_help_still_lists_every_setting():
    r = subprocess.run([sys.executable, "-m", "ballbot_vision.cli", "run", "capture", "--help"],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and "--camera-left" in r.stdout and "BALLBOT_CAPTURE_CAMERA_LEFT" in r.stdout
    r = subprocess.run([sys.executable, "-m", "ballbot_vision.cli", "--help"], capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 0 and "healthcheck" in r.stdout and "calibration" in r.stdout and "obstacles" in r.stdout
    for name in ("viewer", "foxglove"):  # services a person starts by name: `ballbot-vision viewer` = `run viewer`
        r = subprocess.run([sys.executable, "-m", "ballbot_vision.cli", name, "--help"], capture_output=True, text=True,
                           timeout=120)
        assert r.returncode == 0 and "--port" in r.stdout and "--mount-height-m" in r.stdout, r.stderr


_HEAVY_AT_EXIT = ("import atexit, sys\n"
                  "def report():\n"
                  "    heavy = sorted(m for m in sys.modules if m in ('cv2', 'scipy', 'numpy')"
                  " or m.startswith(('services', 'bench')))\n"
                  "    print('HEAVY', heavy, file=sys.stderr, flush=True)\n"
                  "atexit.register(report)\n"
                  "from ballbot_vision import cli\n"
                  "sys.exit(cli.main(sys.argv[1:]))\n")


def test_a_running_router_and_a_real_healthcheck_import_neither_opencv_nor_numpy():
    """Not only their --help: a router that starts, serves and stops, and a healthcheck that
    connects to it and gives its verdict (no segmenter here: 'no healthy stats', exit 1)."""
    import signal

    from helpers import free_port, wait_port

    port = free_port()
    router = subprocess.Popen([sys.executable, "-c", _HEAVY_AT_EXIT, "run", "router", "--listen",
                               f"tcp/127.0.0.1:{port}"], stderr=subprocess.PIPE, text=True)
    try:
        wait_port(port, router)
        # asked for a service that is not running (the router's own stats, once a second, would
        # answer a check of "any service" as healthy whenever they come within the timeout)
        hc = subprocess.run([sys.executable, "-c", _HEAVY_AT_EXIT, "healthcheck", "--connect", f"tcp/127.0.0.1:{port}",
                             "--service", "segmenter", "--timeout", "0.5"], capture_output=True, text=True, timeout=120)
        assert hc.returncode == 1 and "no healthy stats from segmenter" in hc.stderr, hc.stderr
        assert "HEAVY []" in hc.stderr, hc.stderr[-2000:]
    finally:
        router.send_signal(signal.SIGINT)
        err = router.communicate(timeout=60)[1]
    assert router.returncode == 0 and "HEAVY []" in err, err[-2000:]


@pytest.mark.parametrize("case", ["no router", "bad endpoint", "missing config", "bad config", "service, no router"])
def test_zenoh_problems_are_one_line_not_a_traceback(tmp_path, case):
    """A router that does not answer: exit 1 (it may answer later: `up` restarts a service that
    meets it); an endpoint or config file Zenoh refuses: exit 2 (a setting to fix)."""
    from helpers import cli, free_port

    port = free_port()  # nothing listens there
    (tmp_path / "bad.json5").write_text("{ mode: ")
    argv, status, phrase = {
        "no router": (["healthcheck", "--connect", f"tcp/127.0.0.1:{port}", "--timeout", "1"], 1,
                      f"no Zenoh router answers at tcp/127.0.0.1:{port}"),
        "bad endpoint": (["watch", "--mode", "client", "--connect", "localhost:7447", "--timeout", "1"], 2,
                         "--connect localhost:7447: Endpoints must be of the form <protocol>/<address>"),
        "missing config": (["watch", "--zenoh-config", str(tmp_path / "nope.json5"), "--timeout", "1"], 2,
                           f"--zenoh-config {tmp_path / 'nope.json5'}: no such file or folder"),
        "bad config": (["status", "--zenoh-config", str(tmp_path / "bad.json5")], 2,
                       f"--zenoh-config {tmp_path / 'bad.json5'}: not a Zenoh config"),
        "service, no router": (["run", "rectify", "--mode", "client", "--connect", f"tcp/127.0.0.1:{port}"], 1,
                               f"no Zenoh router answers at tcp/127.0.0.1:{port}"),
    }[case]
    r = subprocess.run(cli(*argv), capture_output=True, text=True, timeout=120)
    lines = r.stderr.strip().splitlines()
    assert r.returncode == status and len(lines) == 1 and lines[0].startswith("ballbot-vision: error: "), r.stderr
    assert phrase in r.stderr, r.stderr


def test_a_rule_across_settings_names_each_setting_and_where_it_was_set(tmp_path):
    """A robot lower than the smallest obstacle's top has nothing that could be an obstacle (robot
    height 0.001 m: every street list empty and unflagged); the error names both settings and the file
    and flag each came from."""
    cfg = tmp_path / "robot.yaml"
    cfg.write_text("segmenter:\n  robot_height_m: 0.15\n")
    with pytest.raises(ConfigError) as e:
        load_settings(SegmenterSettings, str(cfg))
    msg = str(e.value)
    assert "robot_height_m (0.15 m) must be above min_height_m (0.2 m)" in msg, msg
    assert f"set by {cfg}: segmenter.robot_height_m)" in msg and "Value error" not in msg, msg
    p = argparse.ArgumentParser()
    add_settings_arguments(p, SegmenterSettings)
    with pytest.raises(ConfigError, match=r"set by .*segmenter.robot_height_m, --min-height-m\)"):
        load_settings(SegmenterSettings, str(cfg), p.parse_args(["--min-height-m", "0.18"]))
    assert load_settings(SegmenterSettings, str(cfg), p.parse_args(["--min-height-m", "0.1"])).robot_height_m == 0.15


@pytest.mark.parametrize("name, value", [("min_height_m", 5), ("min_area_m2", 100), ("min_cell_height_m", 5),
                                         ("min_pixels", 100000), ("min_size_m", 10), ("floor_margin_m", 1),
                                         ("floor_margin_m", 0.02),
                                         ("ground_noise_px", 10), ("group_bin_px", 0.1), ("group_bin_px", 16),
                                         ("merge_gap_m", 10), ("merge_gap_depth_m", 10), ("min_cell_height_m", 0),
                                         ("layer_valley_ratio", 0), ("layer_min_area_m2", 100), ("layer_gap_m", 100),
                                         ("layer_bridge_px", 0), ("layer_split_range_m", 0), ("track_gate_m", 100)])
def test_what_decides_an_obstacle_is_refused_past_where_the_lists_hold_what_stands(tmp_path, name, value):
    """Each of these at an old end of its range emptied or thinned the lists with no degraded reason (the
    street's lists empty at min_height_m 5, min_area_m2 100, min_cell_height_m 5, min_pixels 100000; the
    sway's people merged with the furniture with the depth split off); now a settings error naming it.
    That the lists hold what stands up to the new ends is tests/test_eval.py's (min_pixels':
    tests/test_real_eval.py, on the street)."""
    cfg = tmp_path / "robot.yaml"
    cfg.write_text(f"segmenter:\n  {name}: {value}\n")
    with pytest.raises(ConfigError, match=rf"segmenter\.{name}: .*(less|greater) than or equal"):
        load_settings(SegmenterSettings, str(cfg))


@pytest.mark.parametrize("module, cls, name, value", [
    ("cores.segmentation.settings", "SegmenterSettings", "stale_after_s", 60),
    ("cores.segmentation.settings", "SegmenterSettings", "odometry_timeout_s", 60),
    ("cores.segmentation.settings", "SegmenterSettings", "track_timeout_s", 3600),
    ("services.rectify.main", "RectifySettings", "frozen_after_s", 3600),
    ("services.disparity.main", "DisparitySettings", "max_age_ms", 60000)])
def test_how_long_a_stopped_input_may_go_unsaid_is_seconds_not_an_hour(tmp_path, module, cls, name, value):
    """At frozen_after_s 3600 (allowed before) a camera whose driver hung, repeating its last picture with
    fresh stamps, gave an hour of lists that looked fresh; the segmenter's own frozen and stale checks and
    the age a frame may be started at are bounded alike: 10 s, a refused setting named where it was set."""
    import importlib

    settings = getattr(importlib.import_module(module), cls)
    cfg = tmp_path / "robot.yaml"
    cfg.write_text(f"{settings.section}:\n  {name}: {value}\n")
    with pytest.raises(ConfigError, match=rf"{settings.section}\.{name}: .*less than or equal to 10"):
        load_settings(settings, str(cfg))
    cfg.write_text(f"{settings.section}:\n  {name}: {value / 360}\n")
    assert getattr(load_settings(settings, str(cfg)), name) == value / 360

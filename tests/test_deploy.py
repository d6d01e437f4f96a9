"""The deployment files agree with each other without building anything (the docker tests build):
the pins in deploy/constraints.txt satisfy pyproject.toml's dependencies and the extras the image
carries, so a dependency added without re-locking fails here in seconds, not in step 4 of a
20-minute build; every compose file builds on the base image deploy/build-base-image.sh makes."""
from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import tempfile
import tomllib
from pathlib import Path

import pytest
import yaml
from helpers import REPO
from packaging.requirements import Requirement
from packaging.utils import canonicalize_name


def _pins() -> dict[str, str]:
    pins = {}
    for line in (REPO / "deploy" / "constraints.txt").read_text().splitlines():
        line = line.split("#")[0].strip()
        if "==" in line:
            name, version = line.split("==")
            pins[canonicalize_name(name)] = version.strip()
    return pins


def test_the_image_extras_are_every_runtime_extra():
    extras = subprocess.run([sys.executable, str(REPO / "deploy" / "image-extras.py"), str(REPO / "pyproject.toml")],
                            capture_output=True, text=True, check=True).stdout.strip().split(",")
    declared = tomllib.loads((REPO / "pyproject.toml").read_text())["project"].get("optional-dependencies", {})
    assert set(extras) == set(declared) - {"test", "dev", "docs"}


def test_constraints_pin_every_requirement_of_the_image():
    reqs = subprocess.run([sys.executable, str(REPO / "deploy" / "image-extras.py"), str(REPO / "pyproject.toml"),
                           "--requirements"], capture_output=True, text=True, check=True).stdout.split("\n")
    pins = _pins()
    stale = []
    for text in filter(None, reqs):
        r = Requirement(text)
        if r.marker is not None and not r.marker.evaluate({"python_version": "3.11", "extra": ""}):
            continue
        pinned = pins.get(canonicalize_name(r.name))
        if pinned is None or not r.specifier.contains(pinned, prereleases=True):
            stale.append(f"{text} (pinned: {pinned})")
    assert not stale, ("deploy/constraints.txt does not satisfy pyproject.toml: run deploy/lock-constraints.sh "
                       f"and commit the result; unmet: {', '.join(stale)}")


def test_every_compose_file_builds_on_the_local_base_image():
    tag = subprocess.run(["bash", str(REPO / "deploy" / "build-base-image.sh"), "--print-tag"], capture_output=True,
                         text=True, check=True).stdout.strip()
    assert f"ARG BASE_IMAGE={tag}" in (REPO / "Dockerfile").read_text()
    for f in [REPO / "docker-compose.yml", *(REPO / "deploy").glob("*.compose.yml")]:
        for default in re.findall(r"BASE_IMAGE:-([^}]+)\}", f.read_text()):
            assert default == tag, f"{f.name}: BASE_IMAGE defaults to {default}, the local base image is {tag}"


def test_docker_up_script_parses_and_documents_itself():
    for script in ("docker-up.sh", "build-base-image.sh", "fetch-wheels.sh", "lock-constraints.sh",
                   "calibration-key.sh"):
        subprocess.run(["bash", "-n", str(REPO / "deploy" / script)], check=True)
    out = subprocess.run(["bash", str(REPO / "deploy" / "docker-up.sh"), "--help"], capture_output=True, text=True,
                         check=True).stdout
    assert "docker-compose" in out and "--build-only" in out


def _services(path) -> dict:
    return yaml.safe_load(path.read_text())["services"]  # YAML merge keys (<<: *anchor) resolved


def test_the_robots_containers_share_one_required_calibration_key():
    """capture signs calibrations and rectify checks them with BALLBOT_CALIBRATION_KEY: every robot
    container gets the same one, required (no default a public file would give everyone); offboard
    workers get none."""
    required = "${BALLBOT_CALIBRATION_KEY:?"
    robot_side = {}
    for f in (REPO / "docker-compose.yml", REPO / "deploy" / "robot.compose.yml"):
        for name, svc in _services(f).items():
            command = svc.get("command") or []
            if command[:1] != ["run"] or command[1] == "router":
                continue
            key = (svc.get("environment") or {}).get("BALLBOT_CALIBRATION_KEY")
            if f.name == "docker-compose.yml" and svc.get("networks") == ["offboard"]:
                assert key is None, f"{f.name}: the offboard worker {name} must not hold the robot's key"
                continue
            assert key is not None and key.startswith(required), f"{f.name}: {name} has no required key: {key!r}"
            robot_side[f"{f.name}:{name}"] = key
    assert {"docker-compose.yml:capture", "docker-compose.yml:rectify", "robot.compose.yml:capture",
            "robot.compose.yml:rectify"} <= set(robot_side)
    assert len({v for k, v in robot_side.items() if k.startswith("docker-compose.yml")}) == 1
    for name, svc in _services(REPO / "deploy" / "offboard.compose.yml").items():
        assert "BALLBOT_CALIBRATION_KEY" not in (svc.get("environment") or {}), name
    for ignore in (".gitignore", ".dockerignore"):
        assert ".env" in (REPO / ignore).read_text(), f"{ignore} must keep the key files out"


def test_calibration_key_script_makes_one_key_once_and_keeps_it(tmp_path):
    """deploy/calibration-key.sh (docker-up.sh's step 1): one key in .env and deploy/.env, made
    once, kept on the next run, never printed; a key set in the environment or kept in either file
    wins; another variable's line without its newline is not swallowed."""
    (tmp_path / "deploy").mkdir()
    script = tmp_path / "deploy" / "calibration-key.sh"
    shutil.copy(REPO / "deploy" / "calibration-key.sh", script)

    def run(**env) -> subprocess.CompletedProcess:
        base = {k: v for k, v in os.environ.items() if k not in ("BALLBOT_CALIBRATION_KEY", "SUDO_USER")}
        return subprocess.run(["bash", str(script)], capture_output=True, text=True, check=True, env={**base, **env})

    def keys() -> set[str]:
        return {line.split("=", 1)[1] for f in (tmp_path / ".env", tmp_path / "deploy" / ".env")
                for line in f.read_text().splitlines() if line.startswith("BALLBOT_CALIBRATION_KEY=")}

    (tmp_path / "deploy" / ".env").write_text("BALLBOT_ROBOT_ID=r7")  # no newline at the end
    first = run()
    (key,) = keys()
    assert re.fullmatch(r"[0-9a-f]{64}", key) and key not in first.stdout + first.stderr
    assert "BALLBOT_ROBOT_ID=r7\n" in (tmp_path / "deploy" / ".env").read_text()
    assert (tmp_path / ".env").stat().st_mode & 0o077 == 0
    run()
    assert keys() == {key}
    (tmp_path / ".env").unlink()
    run(BALLBOT_CALIBRATION_KEY="set-by-hand")  # deploy/.env keeps its own; .env gets the one set
    assert {line for line in (tmp_path / ".env").read_text().splitlines()} == {"BALLBOT_CALIBRATION_KEY=set-by-hand"}
    assert key in (tmp_path / "deploy" / ".env").read_text()


def test_compose_refuses_to_start_without_the_key_and_reads_it_from_env_file(tmp_path):
    """What compose itself makes of docker-compose.yml (`config` only: nothing is built or run)."""
    compose = (["docker-compose"] if shutil.which("docker-compose") else
               ["docker", "compose"] if shutil.which("docker") and subprocess.run(
                   ["docker", "compose", "version"], capture_output=True).returncode == 0 else None)
    if compose is None:
        pytest.skip("neither docker-compose nor `docker compose` is installed")
    shutil.copy(REPO / "docker-compose.yml", tmp_path)
    env = {k: v for k, v in os.environ.items() if k != "BALLBOT_CALIBRATION_KEY"}
    r = subprocess.run(compose + ["config"], cwd=tmp_path, capture_output=True, text=True, env=env, timeout=120)
    assert r.returncode != 0 and "calibration-key.sh" in r.stdout + r.stderr, r.stdout + r.stderr
    (tmp_path / ".env").write_text("BALLBOT_CALIBRATION_KEY=k123\n")
    r = subprocess.run(compose + ["--profile", "viewer", "--profile", "ros2", "--profile", "foxglove", "config"],
                       cwd=tmp_path, capture_output=True, text=True, env=env, timeout=120)
    assert r.returncode == 0, r.stderr
    services = yaml.safe_load(r.stdout)["services"]
    with_key = {n for n, s in services.items() if (s.get("environment") or {}).get("BALLBOT_CALIBRATION_KEY") == "k123"}
    assert with_key == {"capture", "rectify", "dispatch", "segmenter", "ros2", "viewer", "foxglove"}, with_key


def _readme_docker_lines() -> list[str]:
    """The Docker commands of README and its pages (docs/deployment.md and the others) as a user
    copies them: the lines of their sh blocks and the inline commands that run Docker or Compose
    (comments cut)."""
    text = "\n".join(p.read_text() for p in [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))])
    lines = []
    for block in re.findall(r"```sh\n(.*?)```", text, re.S):
        for line in block.splitlines():
            cmd = line.split("  #")[0].strip()
            if re.search(r"docker|compose", cmd):
                lines.append(cmd)
    lines += [c for c in re.findall(r"`([^`\n]*(?:compose\.sh|docker-up\.sh)[^`\n]*)`", text) if " " in c]
    return lines


def test_readme_docker_lines_need_neither_sudo_nor_one_compose_version():
    lines = _readme_docker_lines()
    assert any("deploy/compose.sh up -d --scale disparity=3" in l for l in lines), lines
    for line in lines:
        assert not line.startswith("sudo "), f"README: {line!r} needs sudo, which a root machine may not have"
        assert not re.match(r"(\w+=\S+ )*docker[ -]compose\b", line), \
            f"README: {line!r} runs one compose version; deploy/compose.sh runs whichever the machine has"


def _fake_docker(bindir, v2: bool, status: int = 0) -> None:
    """A `docker` (with or without the compose plugin) and, for v1, a `docker-compose` that record
    their arguments, working directory and COMPOSE_PROFILES instead of running anything."""
    record = 'printf "%s\\n" "$PWD" "${COMPOSE_PROFILES:-}" "$*" >"$FAKE_LOG"; exit ' + str(status)
    docker = ('#!/bin/sh\nif [ "$1" = compose ]; then shift; ' + ('[ "$1" = version ] && exit 0; ' + record
              if v2 else 'echo "docker: unknown command: docker compose" >&2; exit 1') + '; fi\nexit 0\n')
    (bindir / "docker").write_text(docker)
    if not v2:
        (bindir / "docker-compose").write_text('#!/bin/sh\n[ "$1" = version ] && { echo 1.29.2; exit 0; }\n'
                                               + record + "\n")
    for f in bindir.iterdir():
        f.chmod(0o755)


@pytest.mark.parametrize("v2", [False, True], ids=["docker-compose-v1", "docker-compose-plugin-v2"])
def test_readme_compose_lines_run_as_written_with_either_compose(tmp_path, v2):
    """Each README line that runs deploy/compose.sh, through bash as written from the repository,
    reaches the machine's compose with exactly its arguments (and its COMPOSE_PROFILES), from the
    repository root where docker-compose.yml is; with a fake docker: nothing is built or started."""
    bindir = tmp_path / "bin"
    bindir.mkdir()
    _fake_docker(bindir, v2)
    lines = [l for l in _readme_docker_lines() if "deploy/compose.sh" in l]
    assert len(lines) >= 3, lines
    env = {**os.environ, "PATH": f"{bindir}:/usr/bin:/bin", "FAKE_LOG": str(tmp_path / "argv")}
    env.pop("COMPOSE_PROFILES", None)
    for line in lines:
        r = subprocess.run(["bash", "-c", line], cwd=REPO, env=env, capture_output=True, text=True, timeout=60)
        assert r.returncode == 0, (line, r.stderr)
        cwd, profiles, argv = (tmp_path / "argv").read_text().splitlines()
        prefix = re.match(r"((?:\w+=\S+ )*)deploy/compose\.sh (.*)", line)
        assert cwd == str(REPO) and argv == prefix.group(2), (line, argv)
        assert profiles == (re.search(r"COMPOSE_PROFILES=(\S+)", prefix.group(1)) or [None, ""])[1]
    which = subprocess.run(["deploy/compose.sh", "--which"], cwd=REPO, env=env, capture_output=True, text=True)
    assert which.stdout.strip() == ("docker compose" if v2 else "docker-compose")


def test_compose_wrapper_names_what_is_missing_and_what_a_non_root_user_needs(tmp_path):
    bindir = tmp_path / "bin"
    bindir.mkdir()
    (bindir / "docker").write_text("#!/bin/sh\nexit 1\n")
    (bindir / "docker").chmod(0o755)
    for tool in ("dirname", "id"):  # what the script needs besides Docker; no docker-compose on this PATH
        (bindir / tool).symlink_to(shutil.which(tool))
    env = {**os.environ, "PATH": str(bindir)}
    r = subprocess.run(["/bin/bash", "deploy/compose.sh", "up", "-d"], cwd=REPO, env=env, capture_output=True,
                       text=True)
    assert r.returncode == 127 and "neither 'docker compose' nor 'docker-compose' is installed" in r.stderr
    setpriv = shutil.which("setpriv")
    if os.geteuid() != 0 or setpriv is None or not os.path.exists("/var/run/docker.sock") \
            or os.stat("/var/run/docker.sock").st_mode & 0o002:
        pytest.skip("the non-root case needs root (to drop to nobody), setpriv and a docker socket nobody may not use")
    shared = Path(tempfile.mkdtemp(prefix="compose-nobody-"))
    try:
        shared.chmod(0o755)
        _fake_docker(shared, v2=False, status=1)
        env = {**os.environ, "PATH": f"{shared}:/usr/bin:/bin", "FAKE_LOG": "/dev/null"}
        env.pop("DOCKER_HOST", None)
        r = subprocess.run([setpriv, "--reuid=65534", "--regid=65534", "--clear-groups", "bash",
                            str(REPO / "deploy" / "compose.sh"), "down"], env=env, capture_output=True, text=True,
                           cwd="/")
        assert r.returncode == 1 and "needs root or the docker group: sudo deploy/compose.sh down" in r.stderr, r.stderr
    finally:
        shutil.rmtree(shared)


def test_readme_compose_profiles_line_gives_the_viewer_and_ros2_services_with_this_machines_compose():
    """The real compose of this machine (v1 or v2) reads the compose file through the wrapper, with
    README's COMPOSE_PROFILES; `config` only: nothing is built or run."""
    if not (shutil.which("docker-compose") or shutil.which("docker")):
        pytest.skip("neither docker-compose nor docker is installed")
    env = {**os.environ, "BALLBOT_CALIBRATION_KEY": "k", "COMPOSE_PROFILES": "viewer,ros2"}
    r = subprocess.run(["deploy/compose.sh", "config", "--services"], cwd=REPO, env=env, capture_output=True,
                       text=True, timeout=120)
    if r.returncode == 127:
        pytest.skip(r.stderr.strip())
    assert r.returncode == 0, r.stderr
    assert {"router", "capture", "segmenter", "viewer", "ros2"} <= set(r.stdout.split())


def test_the_first_readme_command_installs_what_viewer_record_replay_and_foxglove_import():
    """README's first command is `pip install -e .`: every third-party module the viewer, the
    recorder, replay and the Foxglove server import must come with the main dependencies, not an
    extra (only the ROS 2 bridge has one)."""
    import ast
    from importlib.metadata import packages_distributions

    ours = {"ballbot_vision", "bench", "services", "evaluation", "sim", "cores", "common"}
    files = [*(REPO / "services" / "viewer").glob("*.py"), *(REPO / "services" / "recorder").glob("*.py"),
             *(REPO / "services" / "foxglove").glob("*.py"), REPO / "services" / "capture" / "mcap_source.py",
             REPO / "cores" / "recording.py", REPO / "cores" / "recording_reader.py", REPO / "cores" / "foxglove.py",
             REPO / "ballbot_vision" / "mcap_commands.py"]
    modules = set()
    for f in files:
        for node in ast.walk(ast.parse(f.read_text())):
            if isinstance(node, ast.Import):
                modules |= {a.name for a in node.names}
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                modules.add(node.module)
    third_party = {m for m in modules if m.split(".")[0] not in ours | set(sys.stdlib_module_names)}
    assert {"aiohttp", "foxglove", "mcap.writer", "google.protobuf"} <= third_party, third_party
    dists = packages_distributions()
    main = {canonicalize_name(Requirement(r).name)
            for r in tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["dependencies"]}
    missing = {m: dists.get(m.split(".")[0]) for m in third_party
               if not {canonicalize_name(d) for d in dists.get(m.split(".")[0], [])} & main}
    # google.protobuf's top-level package `google` is shared: name the distribution that ships it
    if "google.protobuf" in missing and "protobuf" in main:
        del missing["google.protobuf"]
    assert not missing, f"imported but not in [project].dependencies: {missing}"

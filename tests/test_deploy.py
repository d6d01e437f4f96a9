"""The deployment files agree with each other without building anything (the docker tests build):
the pins in deploy/constraints.txt satisfy pyproject.toml's dependencies and the extras the image
carries, so a dependency added without re-locking fails here in seconds, not in step 4 of a
20-minute build; every compose file builds on the base image deploy/build-base-image.sh makes."""
from __future__ import annotations

import re
import subprocess
import sys
import tomllib

from packaging.requirements import Requirement
from packaging.utils import canonicalize_name

from helpers import REPO


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
    for script in ("docker-up.sh", "build-base-image.sh", "fetch-wheels.sh", "lock-constraints.sh"):
        subprocess.run(["bash", "-n", str(REPO / "deploy" / script)], check=True)
    out = subprocess.run(["bash", str(REPO / "deploy" / "docker-up.sh"), "--help"], capture_output=True, text=True,
                         check=True).stdout
    assert "docker-compose" in out and "--build-only" in out

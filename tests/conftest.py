"""Fixtures and test-session policy; the helpers themselves live in helpers.py.

Docker tests (`-m docker`, tests/test_docker.py) build images for minutes: they run with
`--run-docker` (what .ci/run passes) or BALLBOT_DOCKER_TESTS=1, and are skipped with that reason
otherwise, so README's test command stays quick and needs no Docker. Slow tests (`-m slow`: long
system runs, attacks that last tens of seconds, the real-recording matrix) likewise run with
`--run-slow` (CI passes it) or BALLBOT_SLOW_TESTS=1.

Signals: a shell that starts a job in the background, nohup-style wrappers and some CI runners
start the tests with SIGINT ignored, and an ignored disposition is inherited by every child
process: a test that stops a child with Ctrl-C (SIGINT) would then wait forever. The session
restores the default handling first, so children start with SIGINT as a user's terminal gives it.
"""
from __future__ import annotations

import os
import signal

import pytest
from helpers import Up


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption("--run-docker", action="store_true", default=False,
                     help="run the docker-marked tests (build the images, docker-compose up); "
                          "also BALLBOT_DOCKER_TESTS=1")
    parser.addoption("--run-slow", action="store_true", default=False,
                     help="run the slow-marked tests (long system runs, attacks, the real-recording matrix); "
                          "also BALLBOT_SLOW_TESTS=1")


def pytest_configure(config: pytest.Config) -> None:
    if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)
    for sig in (signal.SIGTERM, signal.SIGHUP):
        if signal.getsignal(sig) is signal.SIG_IGN:
            signal.signal(sig, signal.SIG_DFL)


def _enabled(config: pytest.Config, option: str, env: str) -> bool:
    return bool(config.getoption(option)) or os.environ.get(env, "") in ("1", "true", "yes")


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    skips = {}
    if not _enabled(config, "--run-docker", "BALLBOT_DOCKER_TESTS"):
        skips["docker"] = pytest.mark.skip(reason="docker test: builds images for minutes; run with --run-docker "
                                                  "(CI does, see .ci/run) or BALLBOT_DOCKER_TESTS=1")
    if not _enabled(config, "--run-slow", "BALLBOT_SLOW_TESTS"):
        skips["slow"] = pytest.mark.skip(reason="slow test: run with --run-slow (CI does, see .ci/run) or "
                                                "BALLBOT_SLOW_TESTS=1")
    for item in items:
        for marker, skip in skips.items():
            if marker in item.keywords:
                item.add_marker(skip)


@pytest.fixture
def up():
    u = Up()
    yield u
    u.stop()

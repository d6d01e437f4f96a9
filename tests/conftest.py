"""Fixtures and test-session policy; the helpers themselves live in helpers.py.

Docker tests (`-m docker`, tests/test_docker.py) build images for minutes: they run with
`--run-docker` (what .ci/run passes) or BALLBOT_DOCKER_TESTS=1, and are skipped with that reason
otherwise, so README's test command stays quick and needs no Docker.

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


def pytest_configure(config: pytest.Config) -> None:
    if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)
    for sig in (signal.SIGTERM, signal.SIGHUP):
        if signal.getsignal(sig) is signal.SIG_IGN:
            signal.signal(sig, signal.SIG_DFL)


def docker_tests_enabled(config: pytest.Config) -> bool:
    return bool(config.getoption("--run-docker")) or os.environ.get("BALLBOT_DOCKER_TESTS", "") in ("1", "true", "yes")


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    if docker_tests_enabled(config):
        return
    skip = pytest.mark.skip(reason="docker test: builds images for minutes; run with --run-docker "
                                   "(CI does, see .ci/run) or BALLBOT_DOCKER_TESTS=1")
    for item in items:
        if "docker" in item.keywords:
            item.add_marker(skip)


@pytest.fixture
def up():
    u = Up()
    yield u
    u.stop()

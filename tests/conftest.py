"""Fixtures; the helpers themselves live in helpers.py."""
from __future__ import annotations

import pytest

from helpers import Up


@pytest.fixture
def up():
    u = Up()
    yield u
    u.stop()

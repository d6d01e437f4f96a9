"""The architecture as written in pyproject.toml's import-linter contracts: services side by side,
cores without Zenoh or services, layers, no import loops. A broken contract names the import."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def test_import_contracts_hold():
    lint = Path(sys.executable).with_name("lint-imports")
    out = subprocess.run([str(lint), "--config", str(ROOT / "pyproject.toml")], cwd=ROOT, capture_output=True,
                         text=True, timeout=300)
    assert out.returncode == 0, out.stdout + out.stderr
    assert "0 broken" in out.stdout


def _tool(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", *args], cwd=ROOT, capture_output=True, text=True, timeout=600)


def test_ruff_finds_nothing():
    """ruff with the project's rules ([tool.ruff] in pyproject.toml) over the whole tree, tests too."""
    out = _tool("ruff", "check", ".")
    assert out.returncode == 0, out.stdout + out.stderr


def test_mypy_finds_nothing():
    """mypy with the project's settings ([tool.mypy]: every package, pydantic's plugin)."""
    out = _tool("mypy")
    assert out.returncode == 0, out.stdout + out.stderr


def test_docs_key_table_is_the_key_table():
    from common.keys import TOPICS, markdown_table

    text = (ROOT / "docs" / "keys.md").read_text()
    assert text.endswith(markdown_table()), "docs/keys.md is stale: regenerate it with `ballbot-vision keys --markdown`"
    assert all(f"`{t.template.replace('{', '<').replace('}', '>')}`" in text for t in TOPICS.values())


def test_what_each_service_declares_it_uses_agrees_with_the_key_table():
    """Every service's module declares in its first lines what it subscribes to and publishes
    (openpilot-style); the key table names it as a consumer or producer of each of those topics.
    What a running service really uses is held to its declaration in test_system."""
    import importlib

    from common.keys import TOPICS

    wrong = []
    for folder in sorted(p.parent for p in (ROOT / "services").glob("*/main.py")):
        service = folder.name  # a service folder's name is its process name and its `producer` entry
        m = importlib.import_module(f"services.{service}.main")
        for name in m.SUBSCRIBES:
            t = TOPICS[name]
            if service not in t.consumers and "anyone" not in t.consumers:
                wrong.append(f"{service} subscribes to {name}; the table's consumers: {', '.join(t.consumers)}")
        for name in m.PUBLISHES:
            producers = TOPICS[name].producer.split(", ")
            if service not in producers and "every service" not in producers:
                wrong.append(f"{service} publishes {name}; the table's producer: {TOPICS[name].producer}")
    assert not wrong, "\n".join(wrong)

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


def test_docs_key_table_is_the_key_table():
    from common.keys import TOPICS, markdown_table

    text = (ROOT / "docs" / "keys.md").read_text()
    assert text.endswith(markdown_table()), "docs/keys.md is stale: regenerate it with `ballbot-vision keys --markdown`"
    assert all(f"`{t.template.replace('{', '<').replace('}', '>')}`" in text for t in TOPICS.values())

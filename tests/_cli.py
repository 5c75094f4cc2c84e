"""Shared by the check scripts' CLI tests: a stand-in for a module's ``main``."""

from __future__ import annotations

from pathlib import Path
from typing import Any


def fake_main(monkeypatch, module, out: Path, summary: dict[str, Any]) -> list:
    """Replace ``module.main(run, **options)`` by one that returns
    ``module.Results(out, summary)`` without any work; the list it returns
    gets each call's ``(run, options)``, so a test sees what the CLI passed."""
    calls = []

    def main(run, **kwargs):
        calls.append((run, kwargs))
        return module.Results(out, summary)

    monkeypatch.setattr(module, "main", main)
    return calls

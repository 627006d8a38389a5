"""Tests of the cab box's bundle (systemd/bundle.py) and its install script (systemd/install.sh).

systemd/ is not a package (it holds what goes to /etc and /opt on the box), so the bundle
builder is loaded from its file, once, under the name ``sowgate_bundle``.
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import ModuleType


def _load_bundle() -> ModuleType:
    path = Path(__file__).resolve().parents[2] / "systemd" / "bundle.py"
    spec = importlib.util.spec_from_file_location("sowgate_bundle", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules["sowgate_bundle"] = module  # dataclasses look their module up by name
    spec.loader.exec_module(module)
    return module


bundle = _load_bundle()

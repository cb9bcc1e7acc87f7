"""Every module of the estimation layer imports on its own, first (an import cycle can hide
behind the order in which the app and the other tests import them), and none of them imports
web or database code."""

from __future__ import annotations

import pkgutil
import subprocess
import sys
from pathlib import Path

import server.estimation

ROOT = Path(__file__).resolve().parents[2]
MODULES = sorted(m.name for m in pkgutil.walk_packages(server.estimation.__path__, "server.estimation."))

#: in a fresh interpreter, each module imported first: every ``server`` module is forgotten
#: before the next one (the third-party libraries stay loaded: they cannot be part of a cycle here)
SCRIPT = """
import importlib, sys
failed = []
for name in sys.argv[1:]:
    for loaded in [m for m in sys.modules if m == "server" or m.startswith("server.")]:
        del sys.modules[loaded]
    try:
        importlib.import_module(name)
    except Exception as exc:
        failed.append(f"{name}: {type(exc).__name__}: {exc}")
        continue
    bad = sorted(m for m in sys.modules if m.split(".")[0] in ("fastapi", "starlette", "sqlalchemy", "uvicorn")
                 or m.startswith(("server.api", "server.store", "server.services", "server.db")))
    if bad:
        failed.append(f"{name} imports {bad}")
print("\\n".join(failed))
sys.exit(1 if failed else 0)
"""


def test_each_estimation_module_imports_first_and_without_web_or_database_code():
    assert "server.estimation.floorplan" in MODULES and "server.estimation.tracking.smoother" in MODULES
    done = subprocess.run([sys.executable, "-c", SCRIPT, *MODULES], cwd=ROOT, capture_output=True, text=True,
                          timeout=300)
    assert done.returncode == 0, done.stdout + done.stderr[-2000:]

"""Every module of ``bat3r_core``, ``tasks`` and ``flows`` imports on its own, from a clean slate of project modules:
an import cycle that only bites in one import order, or a module-level side effect (a changed environment, a file
written into the working folder), fails here."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("bat3r_core", "tasks", "flows")

_PROBE = r"""
import importlib, json, os, sys
root, names = sys.argv[1], json.loads(sys.argv[2])
sys.path.insert(0, root)
# third-party packages are imported once up front (some set environment variables on first import: sklearn,
# cv2, bpy); only the project's own modules start afresh for each module probed
import numpy, torch, pyarrow, scipy, sklearn, cv2, open3d, trimesh, prefect
try:
    import bpy
except ImportError:
    pass
failures = []
for name in names:
    for m in [m for m in sys.modules if m.split(".")[0] in ("bat3r_core", "tasks", "flows")]:
        del sys.modules[m]
    env, files = dict(os.environ), sorted(os.listdir("."))
    try:
        importlib.import_module(name)
    except Exception as e:  # noqa: BLE001 - report every module's failure
        failures.append(f"{name}: {type(e).__name__}: {e}")
        continue
    changed = sorted(k for k in set(env) | set(os.environ) if env.get(k) != os.environ.get(k))
    if changed:
        failures.append(f"{name}: importing it changed the environment: {changed}")
    if sorted(os.listdir(".")) != files:
        failures.append(f"{name}: importing it wrote into the working folder: "
                        f"{sorted(set(os.listdir('.')) - set(files))}")
print(json.dumps(failures))
"""


def project_modules() -> list[str]:
    names = []
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            parts = path.relative_to(ROOT).with_suffix("").parts
            names.append(".".join(parts[:-1] if parts[-1] == "__init__" else parts))
    return names


def test_project_modules_are_found():
    names = project_modules()
    assert {"bat3r_core.catalog", "bat3r_core.fitting.config", "tasks.train", "flows.bootstrap"} <= set(names)


def test_every_module_imports_alone(tmp_path):
    names = project_modules()
    out = subprocess.run([sys.executable, "-c", _PROBE, str(ROOT), json.dumps(names)], cwd=tmp_path,
                         capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-3000:]
    failures = json.loads(out.stdout.strip().splitlines()[-1])
    assert failures == [], "\n".join(failures)

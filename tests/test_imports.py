"""Every saft module imports on its own, first (no import cycle), and saft's own imports sit at module top."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

SRC = Path(__file__).resolve().parents[1] / "src"

# One fresh interpreter; before each module every saft.* module is dropped from sys.modules, so each one is
# imported first, as a user's `import saft.x.y` would (torch and the other libraries stay loaded: fast).
_PROBE = r"""
import importlib, sys
failed = []
for name in sys.argv[1:]:
    for loaded in [m for m in sys.modules if m == "saft" or m.startswith("saft.")]:
        del sys.modules[loaded]
    try:
        importlib.import_module(name)
    except Exception as exc:
        failed.append(f"{name}: {type(exc).__name__}: {exc}")
print("\n".join(failed))
sys.exit(1 if failed else 0)
"""


def _modules() -> list[str]:
    names = []
    for path in sorted((SRC / "saft").rglob("*.py")):
        parts = path.relative_to(SRC).with_suffix("").parts
        if parts[-1] == "__main__":  # runs the CLI when imported
            continue
        names.append(".".join(parts[:-1] if parts[-1] == "__init__" else parts))
    return names


def test_every_module_imports_first_without_a_cycle():
    names = _modules()
    assert len(names) > 50 and "saft.render.torch.fused" in names
    res = subprocess.run([sys.executable, "-c", _PROBE, *names], capture_output=True, text=True,
                         env={**os.environ, "PYTHONPATH": str(SRC)}, timeout=300)
    assert res.returncode == 0, res.stdout + res.stderr


def test_saft_imports_are_at_module_top():
    """Inside functions only heavy optional libraries are imported lazily, never saft's own modules."""
    local = re.compile(r"^\s+(from saft[\w.]* import|import saft\b|from \.)")
    offenders = [f"{p.relative_to(SRC)}:{i}" for p in sorted((SRC / "saft").rglob("*.py"))
                 for i, line in enumerate(p.read_text().splitlines(), 1) if local.match(line)]
    assert offenders == []

"""Fixtures of the evaluation tests: where the φ-SfT R1 data is (../shared beside the repository)."""

from __future__ import annotations

from pathlib import Path

import pytest

_REPO = Path(__file__).resolve().parents[2]
_R1 = (_REPO / ".." / "shared" / "data" / "phi_sft").resolve()


@pytest.fixture(scope="session")
def r1_data() -> dict[str, Path]:
    """Paths of the R1 template and ground-truth folder; skips when ../shared is not there."""
    template = _R1 / "data" / "R1" / "0_R1_quad.obj"
    gt_dir = _R1 / "evaluation" / "R1" / "ground_truth"
    if not template.is_file() or not (gt_dir / "point_cloud_000.pt").is_file():
        pytest.skip(f"R1 data not found under {_R1} (the shared/ folder beside the repository)")
    return {"template": template, "gt_dir": gt_dir}

"""Fixtures of the reconstruction tests."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest


@pytest.fixture
def tiny_reconstruction(tmp_path):
    """A function: reconstruct a 6-frame, 48 × 48 hanging cloth with a short schedule and `sets` (--set
    key=value strings) into tmp_path/out; checks the result is finite and returns the result folder."""
    from saft.config_io import load_config
    from saft.reconstruct import SaftConfig, reconstruct
    from saft.result import read_result
    from saft.scene import load_scene
    from saft.synthetic import HangingClothSpec, write_hanging_cloth

    def run(sets: list[str]) -> Path:
        spec = HangingClothSpec(grid=6, size=0.4, frames=6, image_size=48, focal=92.0, texture_size=32,
                                gt_points=200)
        scene = load_scene(write_hanging_cloth(tmp_path / "scene", spec))
        cfg = load_config(SaftConfig, None, ["texture.epochs=5", "texture.size=32", 'run.device="cpu"',
                                             "appearance.enabled=false", "shape.window=2",
                                             "shape.add_frame_every=2", "shape.final_epochs=2", *sets])
        reconstruct(scene, cfg, tmp_path / "out", quiet=True)
        assert np.isfinite(read_result(tmp_path / "out").vertices).all()
        return tmp_path / "out"

    return run

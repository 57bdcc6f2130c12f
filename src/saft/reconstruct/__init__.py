"""saft.reconstruct: the phases that turn a Scene into a result folder.

- config.py       SaftConfig: every hyperparameter with the published defaults (saved as config.toml)
- texture_phase   phase 1: texture mapping on frame 0 (paper 3.3.1)
- shape_phase     phase 2: physics-based shape from template with R_E and R_F (paper 3.3.2)
- losses.py       image, silhouette, FD smoothness, R_F
- optim.py        per-parameter Adam with clipping, non-finite skipping and AutoClip
- checkpoint.py   resume state written between epochs; Ctrl-C ends at an epoch boundary
- pipeline.py     reconstruct(scene, cfg, out_dir, resume=...) sequences the phases and writes the result
- outputs.py      meshes, texture, params, forces, renders
"""

from saft.reconstruct.config import SaftConfig, shape_schedule
from saft.reconstruct.pipeline import RunOutcome, reconstruct

__all__ = ["RunOutcome", "SaftConfig", "reconstruct", "shape_schedule"]

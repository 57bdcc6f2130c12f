"""saft.reconstruct: the phases that turn a Scene into a result folder.

- config.py       SaftConfig: every hyperparameter with the published defaults (saved as config.toml)
- context.py      PhaseContext: what every phase shares, checkpoint() / check_interrupt() / epoch_done()
- texture_phase   phase 1: texture mapping on frame 0 (paper 3.3.1)
- shape_phase     phase 2: physics-based shape from template with R_E and R_F (paper 3.3.2)
- losses.py       image, silhouette, FD smoothness, R_F
- initial_velocity  the learned velocity at frame 0 (affine, started from the tracks) and its prior R_V
- optim.py        per-parameter Adam with clipping, non-finite skipping and AutoClip
- checkpoint.py   resume state written between epochs; Ctrl-C ends at an epoch boundary
- config_checks   numeric ranges of the config (one line naming the key)
- out_dir.py      what --out may be; --overwrite clears an old result
- run_identity    scene digests + result-determining config keys, checked by --resume
- estimate.py     time and memory of the run, measured before the first epoch
- pipeline.py     reconstruct(scene, cfg, out_dir, resume=..., overwrite=...) loops over the PHASES table
- outputs.py      meshes, texture, params, forces, renders
- appearance_outputs  phase 3 in a run (saft.appearance) and its material/ renders
"""

from saft.reconstruct.config import SaftConfig, shape_schedule
from saft.reconstruct.pipeline import RunOutcome, reconstruct

__all__ = ["RunOutcome", "SaftConfig", "reconstruct", "shape_schedule"]

"""The shape phase's loss weights of a swinging run (issue 29; not in the paper).

Where the swing trial (saft.reconstruct.swing_damping) picks physics.swing_damping, the cloth swings from one
corner under gravity: it moves fast, and its point tracks die in the swing's second half (Newton one corner:
39 % valid at frame 12, 9 % at 15, none from frame 20), so the late frames are fitted from the images alone.
There the reconstruction's silhouette error stays 3-13x the truth's (the truth placed on the template;
benchmarks/diagnose_independent.py): the silhouette term, at the paper's weight, does not pull the cloth
into the mask. shape.swing_lambda_sil > 0 replaces shape.lambda_sil in such a run; elsewhere (the trial keeps
the default damping) the config is returned as it is, and the run is the option's off, bit for bit.
"""

from __future__ import annotations

import dataclasses
import logging

from saft.reconstruct.config import PhysicsConfig, ShapeConfig

log = logging.getLogger("saft")


def swing_shape_config(cfg: ShapeConfig, phys: PhysicsConfig, damping: float) -> ShapeConfig:
    """`cfg` with lambda_sil = cfg.swing_lambda_sil where the run's damping (the trial's choice, checkpointed
    with the run, so a resumed run agrees) is not physics.damping and the option is on (> 0); else `cfg`."""
    if cfg.swing_lambda_sil <= 0 or damping == phys.damping:
        return cfg
    log.info("silhouette weight %.4g in this swinging run (shape.swing_lambda_sil)", cfg.swing_lambda_sil)
    return dataclasses.replace(cfg, lambda_sil=cfg.swing_lambda_sil)


__all__ = ["swing_shape_config"]

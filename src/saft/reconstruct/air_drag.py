"""Where the shape phase keeps the learned air drag (physics.air_drag, saft.physics.drag; issue 29, not in the paper).

The drag is a brake on the cloth's motion along its normal. Under the paper's velocity damping (0.9 per
substep, an "ether" damping that already brakes every motion) it is a second brake, and where wind drives the
cloth it opposes the learned accelerations that stand for the wind: on the Newton scenes driven by wind it made
the late gust 2.5x worse (1.13 -> 2.86) and the fold +16 %, while the cloth swinging from one corner, run with
the low swing damping (saft.reconstruct.swing_damping), gained 20 % (12.35 -> 9.94; BENCHMARKS "Air drag").
Hence physics.air_drag_where: "swing" keeps the drag only where the swing trial chose the low damping (the drag
takes over the braking that the lowered ether damping gave up); "always" keeps it everywhere. Where it is
dropped, before the first epoch, the run is the option's off, bit for bit. The swing trial itself runs without
the drag either way, so that it chooses as it does without the option.
"""

from __future__ import annotations

import logging

from saft.reconstruct.swing_damping import run_damping

log = logging.getLogger("saft")


def run_damping_and_drag(state, sim, tracks, camera, phys) -> float:
    """run_damping (its trial without the drag), then the drag kept or dropped by physics.air_drag_where
    (`state`: ShapeState before its first epoch of this process; a resumed run's parameters already hold the
    drag or not, as its first start left them)."""
    drag, state.params.log10_drag = state.params.log10_drag, None
    try:
        chosen = run_damping(state, sim, tracks, camera, phys)
    finally:
        state.params.log10_drag = drag
    if drag is not None and phys.air_drag_where == "swing" and chosen == phys.damping:
        state.params.log10_drag = None
        state.optimizer.drop("log10_drag")
        log.info("air drag off: the run keeps the damping %.4g (physics.air_drag_where = \"swing\")", chosen)
    return chosen


__all__ = ["run_damping_and_drag"]

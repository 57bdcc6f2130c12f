"""saft.synthetic — synthetic scenes made with saft's own components, for the demo, tests and benchmarks.

- hanging_cloth   a square cloth hanging from its top edge, blown by a gust: simulated (saft.physics),
                  rendered (saft.render), with a ground-truth point cloud per frame; written as a native
                  scene folder (saft.scene) — what `saft demo` reconstructs
- appearance      a cloth sheet with known SVBRDF maps and environment map, rendered with Mitsuba
                  (saft.appearance): the appearance phase's tests and benchmark
- benchmark_scenes  wind, swing, fold: simulated by saft.physics on the template's mesh, path-traced by Mitsuba
- newton_cloth      a cloth simulated by NVIDIA Newton's VBD solver (not saft's model; newton imported lazily)
- independent_scenes  benchmark scenes from Newton on a finer mesh, with saft-simulated (model-matched) twins
- mid_motion        a written scene without its first frames: a clip that starts mid-motion

It sits above scene/, physics/, render/ and evaluate/ so that those do not import each other for it.
"""

from saft.synthetic.hanging_cloth import (HangingClothSpec, grid_template, gust_accelerations, make_hanging_cloth,
                                          procedural_texture, write_hanging_cloth)

__all__ = ["HangingClothSpec", "grid_template", "gust_accelerations", "make_hanging_cloth", "procedural_texture",
           "write_hanging_cloth"]

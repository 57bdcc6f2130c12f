"""saft.synthetic — synthetic scenes made with saft's own components, for the demo, tests and benchmarks.

- hanging_cloth   a square cloth hanging from its top edge, blown by a gust: simulated (saft.physics),
                  rendered (saft.render), with a ground-truth point cloud per frame; written as a native
                  scene folder (saft.scene) — what `saft demo` reconstructs
- appearance      a cloth sheet with known SVBRDF maps and environment map, rendered with Mitsuba
                  (saft.appearance): the appearance phase's tests and benchmark

It sits above scene/, physics/, render/ and evaluate/ so that those do not import each other for it.
"""

from saft.synthetic.hanging_cloth import (HangingClothSpec, grid_template, gust_accelerations, make_hanging_cloth,
                                          procedural_texture, write_hanging_cloth)

__all__ = ["HangingClothSpec", "grid_template", "gust_accelerations", "make_hanging_cloth", "procedural_texture",
           "write_hanging_cloth"]

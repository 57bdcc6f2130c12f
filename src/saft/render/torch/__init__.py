"""The PyTorch rasterizer: nvdiffrast's four primitives in vectorised torch, for any device.

One module per operation, as in nvdiffrast: raster (visibility and barycentrics), interpolate, texture
(lookup and the mip pyramid), antialias; rows holds the scatter/gather autograd functions they share. These
are the readable reference. fused holds the fast path of render_cloth (everything on the covered pixels,
hand-written backwards), tested against the primitives as Mitsuba tests prb.py against prb_basic.py.
rasterizer holds TorchRasterizer, the backend object. The package exports only TorchRasterizer, so that
the operation modules keep their names (saft.render.torch.texture is the module, not the function).
"""

from saft.render.torch.rasterizer import TorchRasterizer

__all__ = ["TorchRasterizer"]

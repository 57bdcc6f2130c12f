"""The per-mesh constants of a render: the triangle list as int64 on the device, its transposes, and the
triangle across each edge (for silhouette detection), made once per triangle list and cached, so that a
frame's render does no host work, copy or sync for them."""

from __future__ import annotations

import hashlib
import weakref
from collections import OrderedDict

import numpy as np
import torch

_CACHE: "OrderedDict[tuple, Topology]" = OrderedDict()  # by content: the fallback, one hash per call
_CACHE_SIZE = 16


class TensorCache:
    """Values derived from tensors, found by the tensor's identity: a tensor seen before and unmodified since
    (the same object, the same _version) gets the value put for it, with no copy, hash or host sync. An entry
    goes when its tensor is freed; with `limit`, the oldest also goes when a new one would exceed it. `key`:
    what else the value depends on (a device, a mip level...)."""

    def __init__(self, limit: int | None = None):
        self._entries: dict = {}
        self.limit = limit

    def get(self, t: torch.Tensor, *key):
        hit = self._entries.get((id(t), *key))
        if hit is not None and hit[0]() is t and hit[1] == t._version:
            return hit[2]
        return None

    def put(self, t: torch.Tensor, value, *key):
        k = (id(t), *key)
        if self.limit is not None and k not in self._entries and len(self._entries) >= self.limit:
            self._entries.pop(next(iter(self._entries)))
        entries = self._entries
        entries[k] = (weakref.ref(t, lambda _r: entries.pop(k, None)), t._version, value)
        return value


_BY_ID = TensorCache()  # by tensor identity: (tensor, device) → weakref to the Topology


def edge_neighbors_np(tri: np.ndarray) -> np.ndarray:
    """(T, 3) int64: for edge k of triangle t (vertices tri[t, k] → tri[t, (k+1) % 3]) the other triangle
    sharing that undirected edge, or −1 where the edge is on the boundary. With non-manifold edges (three
    or more triangles) each triangle gets one of the others."""
    tri = np.asarray(tri, dtype=np.int64)
    T = tri.shape[0]
    a = tri
    b = np.roll(tri, -1, axis=1)
    lo, hi = np.minimum(a, b).reshape(-1), np.maximum(a, b).reshape(-1)
    key = lo * (int(tri.max(initial=0)) + 1) + hi
    order = np.argsort(key, kind="stable")
    ks = key[order]
    nbr = np.full(3 * T, -1, dtype=np.int64)
    same = ks[1:] == ks[:-1]
    i = np.nonzero(same)[0]
    # pair consecutive equal keys both ways (for manifold meshes exactly two entries per interior edge)
    nbr[order[i]] = order[i + 1] // 3
    nbr[order[i + 1]] = np.where(nbr[order[i + 1]] < 0, order[i] // 3, nbr[order[i + 1]])
    return nbr.reshape(T, 3)


class Topology:
    """tri (T, 3) int64; triT (3, T) and tri_flat_t = triT.reshape(-1) (vertex k of every triangle, then
    k+1: gathers whose backward is one index_add); nbr (T, 3) the triangle across each edge or −1;
    boundary (T, 3) nbr < 0; nb (T, 3) nbr clamped to a valid index. All on one device. tri32: tri as
    contiguous int32 (nvdiffrast's index type), made on first use; backend_cache: what a backend derives
    from the triangles once (nvdiffrast's antialias topology hash)."""

    def __init__(self, tri: torch.Tensor):
        self.tri = tri
        self.triT = tri.T.contiguous()
        self.tri_flat_t = self.triT.reshape(-1)
        self.nbr = torch.from_numpy(edge_neighbors_np(tri.cpu().numpy())).to(tri.device)
        self.boundary = self.nbr < 0
        self.nb = self.nbr.clamp(min=0)
        self._batched: dict = {}
        self._tri32 = None
        self.backend_cache: dict = {}

    @property
    def tri32(self) -> torch.Tensor:
        if self._tri32 is None:
            self._tri32 = self.tri.to(torch.int32).contiguous()
        return self._tri32

    def batched_triT(self, B: int, V: int) -> torch.Tensor:
        """(3, B·T): vertex k of triangle t of image b as a row of the flattened (B·V) vertices."""
        out = self._batched.get((B, V))
        if out is None:
            off = torch.arange(B, device=self.tri.device).repeat_interleave(self.tri.shape[0]) * V
            out = self._batched[(B, V)] = self.triT.repeat(1, B) + off
        return out


def topology(triangles, device: torch.device | str | None = None) -> Topology:
    """The Topology of a triangle list (tensor or array, any int dtype) on `device` (default: the tensor's
    own, else the CPU). A tensor seen before, unmodified (same object, same _version), is found by identity
    (no copy to the host); anything else by a hash of its contents."""
    is_t = isinstance(triangles, torch.Tensor)
    dev = torch.device(device) if device is not None else (triangles.device if is_t else torch.device("cpu"))
    if is_t:
        hit = _BY_ID.get(triangles, dev)
        topo = hit() if hit is not None else None
        if topo is not None:
            return topo
    arr = (triangles.detach().to("cpu") if is_t else torch.as_tensor(np.asarray(triangles))).to(torch.int64)
    arr = arr.contiguous().numpy()
    key = (hashlib.blake2b(arr.tobytes(), digest_size=16).hexdigest(), arr.shape, str(dev))
    topo = _CACHE.get(key)
    if topo is None:
        topo = Topology(torch.from_numpy(arr).to(dev))
        _CACHE[key] = topo
        if len(_CACHE) > _CACHE_SIZE:
            _CACHE.popitem(last=False)
    else:
        _CACHE.move_to_end(key)
    for t in ((triangles, topo.tri) if is_t else (topo.tri,)):
        # weak both ways: the table keeps neither a caller's tensor nor a Topology the content cache dropped
        _BY_ID.put(t, weakref.ref(topo), dev)
    return topo


def edge_neighbors(tri: torch.Tensor) -> torch.Tensor:
    """edge_neighbors_np for a tensor, cached (see topology)."""
    return topology(tri).nbr

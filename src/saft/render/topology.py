"""Triangle adjacency for silhouette detection: the triangle across each edge (or −1 on the boundary)."""

from __future__ import annotations

import hashlib
from collections import OrderedDict

import numpy as np
import torch

_CACHE: "OrderedDict[tuple, torch.Tensor]" = OrderedDict()
_CACHE_SIZE = 16


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


def edge_neighbors(tri: torch.Tensor) -> torch.Tensor:
    """edge_neighbors_np for a tensor, cached by the triangle list's contents (cheap to call per frame)."""
    arr = tri.detach().to("cpu", torch.int64).contiguous().numpy()
    key = (hashlib.blake2b(arr.tobytes(), digest_size=16).hexdigest(), arr.shape, str(tri.device))
    hit = _CACHE.get(key)
    if hit is not None:
        _CACHE.move_to_end(key)
        return hit
    out = torch.from_numpy(edge_neighbors_np(arr)).to(tri.device)
    _CACHE[key] = out
    if len(_CACHE) > _CACHE_SIZE:
        _CACHE.popitem(last=False)
    return out

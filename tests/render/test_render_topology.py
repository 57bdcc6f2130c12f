"""The per-mesh constants of a render (saft.render.topology): made once, found again without a copy."""

from __future__ import annotations

import numpy as np
import torch

from saft.render.reference import texture_uv
from saft.render.topology import TensorCache, edge_neighbors_np, topology


def test_topology_is_cached_by_identity_and_by_contents():
    tri = torch.tensor([[0, 1, 2], [2, 1, 3]], dtype=torch.int32)
    topo = topology(tri)
    assert topo.tri.dtype == torch.int64 and torch.equal(topo.tri, tri.long())
    assert topology(tri) is topo and topology(topo.tri) is topo
    assert topology(np.array([[0, 1, 2], [2, 1, 3]])) is topo  # same contents
    np.testing.assert_array_equal(topo.nbr.numpy(), edge_neighbors_np(tri.numpy()))
    assert torch.equal(topo.triT, tri.long().T) and torch.equal(topo.tri_flat_t, tri.long().T.reshape(-1))
    assert torch.equal(topo.batched_triT(2, 4), torch.cat([tri.long().T, tri.long().T + 4], dim=1))
    tri[1, 2] = 0  # changed in place: not the cached one any more
    other = topology(tri)
    assert other is not topo and int(other.tri[1, 2]) == 0


def test_tensor_cache_finds_an_unmodified_tensor_and_forgets_a_freed_one():
    cache = TensorCache(limit=2)
    a, b, c = torch.zeros(3), torch.ones(3), torch.full((3,), 2.0)
    assert cache.get(a) is None
    assert cache.put(a, "a", "cpu") == "a" and cache.get(a, "cpu") == "a" and cache.get(a, "cuda") is None
    assert cache.get(torch.zeros(3), "cpu") is None          # equal contents, another tensor
    a.add_(1)                                                  # modified in place: stale
    assert cache.get(a, "cpu") is None
    cache.put(a, "a1", "cpu")
    cache.put(b, "b")
    cache.put(c, "c")                                          # over the limit: the oldest entry goes
    assert cache.get(a, "cpu") is None and cache.get(b) == "b" and cache.get(c) == "c"
    del b
    assert len(cache._entries) == 1                            # a freed tensor's entry goes with it


def test_texture_uv_is_made_once_per_uv_tensor():
    uv = torch.tensor([[0.25, 0.0], [1.0, 0.75]])
    out = texture_uv(uv)
    assert torch.equal(out, torch.tensor([[0.25, 1.0], [1.0, 0.25]])) and texture_uv(uv) is out
    uv[0, 1] = 0.5
    assert texture_uv(uv) is not out and float(texture_uv(uv)[0, 1]) == 0.5

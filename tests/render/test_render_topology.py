"""The per-mesh constants of a render (saft.render.topology): made once, found again without a copy."""

from __future__ import annotations

import numpy as np
import torch

from saft.render.topology import edge_neighbors_np, topology


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

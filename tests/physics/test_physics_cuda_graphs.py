"""CUDA graphs around fixed-shape functions (saft.physics.cuda_graphs)."""

import pytest
import torch

from saft.physics.cuda_graphs import Graphed, graphs_wanted


def _f(x, k):
    return (x * k).sin() + x.square().sum(), x.cumsum(0)


def test_on_the_cpu_it_is_a_plain_call():
    assert not graphs_wanted(torch.device("cpu"))
    g = Graphed(_f, record=False)
    x, k = torch.randn(5), torch.tensor(2.0)
    assert g.graph is None
    for a, b in zip(g(x, k), _f(x, k)):
        assert torch.equal(a, b)


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs an NVIDIA GPU")
def test_replays_give_the_eager_result_for_new_inputs():
    dev = torch.device("cuda")
    assert graphs_wanted(dev, True) and not graphs_wanted(dev, False)
    x, k = torch.randn(1000, device=dev, dtype=torch.float64), torch.tensor(2.0, device=dev, dtype=torch.float64)
    g = Graphed(_f, (x, k))
    assert g.graph is not None
    for _ in range(3):
        x = torch.randn_like(x)  # a new tensor each call is copied in; k, the same object, is not copied again
        out = [o.clone() for o in g(x, k)]
        for a, b in zip(out, _f(x, k)):
            assert torch.equal(a, b)
    k2 = torch.tensor(-1.0, device=dev, dtype=torch.float64)
    for a, b in zip(g(x, k2), _f(x, k2)):
        assert torch.equal(a, b)

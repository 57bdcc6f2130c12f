"""The device plan: where `--device auto|cpu|cuda` puts the physics, the renders and the appearance phase.
The CUDA branches are checked here on any machine by stating what a GPU machine would report (torch sees
a device; nvdiffrast and Mitsuba's CUDA variant work or not); tests/reconstruct/test_reconstruct_cuda.py
runs the plan for real where there is a GPU."""

import pytest
import torch

import saft.device as D
from saft.errors import SaftInputError


def test_cpu_machine_puts_every_part_on_the_cpu(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    for name, why in (("auto", "no CUDA device"), ("cpu", "asked for (--device cpu)")):
        plan = D.plan_devices(name)
        assert (plan.physics.type, plan.render.type, plan.appearance.type) == ("cpu", "cpu", "cpu")
        assert all(why in line for line in plan.lines())
    with pytest.raises(SaftInputError, match="cuda was asked for"):
        D.plan_devices("cuda")


def test_gpu_machine_auto_keeps_each_part_where_it_is_fastest(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    plan = D.plan_devices("auto", nvdiffrast_ok=True, mitsuba_cuda_ok=True)
    assert plan.render.type == "cuda" and plan.appearance.type == "cuda"
    assert plan.physics.type == "cuda" and "dense" in plan.why["physics"]
    assert "nvdiffrast" in plan.why["render"]
    big = D.plan_devices("auto", vertices=D.PHYSICS_CUDA_MAX_VERTICES + 1, nvdiffrast_ok=True, mitsuba_cuda_ok=True)
    assert big.physics.type == "cpu" and big.render.type == "cuda"
    no_mitsuba = D.plan_devices("auto", nvdiffrast_ok=False, mitsuba_cuda_ok=False)
    assert no_mitsuba.render.type == "cuda" and no_mitsuba.appearance.type == "cpu"
    assert "PyTorch rasterizer" in no_mitsuba.why["render"] and "llvm_ad_rgb" in no_mitsuba.why["appearance"]
    assert D.plan_devices("auto", appearance=False, nvdiffrast_ok=True).appearance.type == "cpu"
    forced_torch = D.plan_devices("auto", rasterizer="torch", nvdiffrast_ok=True, mitsuba_cuda_ok=True)
    assert "render.backend = torch" in forced_torch.why["render"]


def test_gpu_machine_cuda_puts_every_part_on_the_gpu(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    plan = D.plan_devices("cuda", nvdiffrast_ok=True, mitsuba_cuda_ok=False)
    assert {plan.physics.type, plan.render.type, plan.appearance.type} == {"cuda"}
    assert "not usable here" in plan.why["appearance"]


def test_appearance_profile_follows_the_appearance_device(monkeypatch):
    from saft.reconstruct.config import load_saft_config

    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(D, "_mitsuba_cuda_ok", lambda: False)
    assert D.appearance_device("auto").type == "cpu"
    assert load_saft_config(None, ['run.device="auto"']).appearance.profile == "cpu"
    monkeypatch.setattr(D, "_mitsuba_cuda_ok", lambda: True)
    assert D.appearance_device("auto").type == "cuda"
    assert load_saft_config(None, ['run.device="auto"']).appearance.profile == "cuda"


def test_physics_device_override_for_ab_runs(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    for forced in ("cpu", "cuda"):
        monkeypatch.setenv(D.ENV_PHYSICS_DEVICE, forced)
        plan = D.plan_devices("auto", nvdiffrast_ok=True, mitsuba_cuda_ok=True)
        assert plan.physics.type == forced and D.ENV_PHYSICS_DEVICE in plan.why["physics"]
    monkeypatch.setenv(D.ENV_PHYSICS_DEVICE, "cuda")
    assert D.plan_devices("cpu").physics.type == "cpu"   # only auto's choice is overridden

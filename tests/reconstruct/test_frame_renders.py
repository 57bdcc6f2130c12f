"""How many threads render the shape phase's frames (saft.reconstruct.frame_renders)."""

import os

import torch

from saft.reconstruct.frame_renders import render_chunk, render_threads


def test_render_threads_follow_the_request_else_the_cores_on_the_cpu_only(monkeypatch):
    assert render_threads(3, "cpu") == 3
    assert render_threads(2, torch.device("cuda")) == 2
    assert render_threads(0, torch.device("cuda")) == 1   # one stream: the GPU batches chunks instead
    for cores, want in ((1, 1), (2, 2), (3, 3), (16, 4)):
        monkeypatch.setattr(os, "cpu_count", lambda c=cores: c)
        assert render_threads(0, "cpu") == want


def test_chunks_are_single_frames_on_the_cpu_and_batches_on_a_gpu():
    assert render_chunk("cpu") == 1
    assert render_chunk(torch.device("cuda")) == 8

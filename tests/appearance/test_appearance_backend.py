"""The Mitsuba backend check: variant by device, and a missing / too-old LLVM gives one clear line."""

import os
import subprocess
import sys
from pathlib import Path

import pytest

from saft.appearance.mitsuba_backend import INSTALL_HINT, _llvm_version_of, find_llvm_candidates, variant_for_device

SRC = str(Path(__file__).resolve().parents[2] / "src")

CHECK = """
from saft.appearance.mitsuba_backend import ensure_backend
from saft.errors import BackendUnavailableError
try:
    ensure_backend('cpu')
    print('AVAILABLE')
except BackendUnavailableError as exc:
    print('ERROR:' + str(exc))
"""


def _run_check(llvm_path: str) -> subprocess.CompletedProcess:
    env = dict(os.environ, DRJIT_LIBLLVM_PATH=llvm_path, PYTHONPATH=SRC + os.pathsep + os.environ.get("PYTHONPATH", ""))
    return subprocess.run([sys.executable, "-c", CHECK], env=env, capture_output=True, text=True, timeout=300)


def test_variant_for_device():
    assert variant_for_device("cpu") == "llvm_ad_rgb"
    assert variant_for_device("cuda:0") == "cuda_ad_rgb"
    with pytest.raises(ValueError):
        variant_for_device("mps")


def test_llvm_version_from_file_name():
    assert _llvm_version_of("/usr/lib/x86_64-linux-gnu/libLLVM-19.so")[0] == 19
    assert _llvm_version_of("/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1")[0] == 19
    assert _llvm_version_of("/usr/lib/llvm-15/lib/libLLVM.so")[0] == 15


def test_missing_llvm_gives_one_line(tmp_path):
    proc = _run_check(str(tmp_path / "no-such-libLLVM.so"))
    assert proc.returncode == 0, proc.stderr[-2000:]
    lines = [ln for ln in proc.stdout.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("ERROR:"), proc.stdout
    assert INSTALL_HINT in lines[0] and "\n" not in lines[0]


def test_too_old_llvm_is_named(tmp_path):
    # a bogus "LLVM 15" library: it cannot load, and the message names the version and the fix
    fake = tmp_path / "libLLVM-15.so"
    fake.write_bytes(b"not a library")
    proc = _run_check(str(fake))
    lines = [ln for ln in proc.stdout.splitlines() if ln.strip()]
    assert len(lines) == 1 and "LLVM 15" in lines[0] and INSTALL_HINT in lines[0], proc.stdout + proc.stderr[-2000:]


@pytest.mark.skipif(not Path("/usr/lib/x86_64-linux-gnu/libLLVM-15.so.1").exists(), reason="no real LLVM 15 here")
def test_real_llvm15_does_not_crash_the_caller():
    # LLVM 15 loads but aborts while compiling ("Cannot select: fminimum"): the probe runs in a subprocess
    proc = _run_check("/usr/lib/x86_64-linux-gnu/libLLVM-15.so.1")
    lines = [ln for ln in proc.stdout.splitlines() if ln.strip()]
    assert proc.returncode == 0 and len(lines) == 1
    assert "LLVM 15" in lines[0] and INSTALL_HINT in lines[0]


def test_candidates_are_new_enough():
    for path in find_llvm_candidates():
        assert _llvm_version_of(path)[0] >= 19


def test_default_lookup_failure_selects_a_found_llvm(monkeypatch):
    # when the default lookup fails and the user set nothing, a found LLVM >= 19 goes into DRJIT_LIBLLVM_PATH
    import saft.appearance.mitsuba_backend as mb

    calls = []

    def fake_probe(variant, env, timeout=120.0):
        calls.append(env.get("DRJIT_LIBLLVM_PATH"))
        if env.get("DRJIT_LIBLLVM_PATH") == "/opt/llvm-21/lib/libLLVM.so.21.1":
            return True, "LLVM 21.1.0\nOK"
        return False, "jit_init_thread_state(): the LLVM backend is inactive"

    monkeypatch.delenv("DRJIT_LIBLLVM_PATH", raising=False)
    monkeypatch.setattr(mb, "_checked", {})
    monkeypatch.setattr(mb, "_probe", fake_probe)
    monkeypatch.setattr(mb, "find_llvm_candidates", lambda min_major=19: ["/opt/llvm-21/lib/libLLVM.so.21.1"])
    try:
        assert mb.ensure_backend("cpu") == "llvm_ad_rgb"
        assert calls == [None, "/opt/llvm-21/lib/libLLVM.so.21.1"]
        assert os.environ["DRJIT_LIBLLVM_PATH"] == "/opt/llvm-21/lib/libLLVM.so.21.1"
    finally:
        os.environ.pop("DRJIT_LIBLLVM_PATH", None)  # set by ensure_backend itself, not by monkeypatch

    # nothing found: one line naming the package to install
    monkeypatch.setattr(mb, "_checked", {})
    monkeypatch.setattr(mb, "find_llvm_candidates", lambda min_major=19: [])
    with pytest.raises(mb.BackendUnavailableError) as info:
        mb.ensure_backend("cpu")
    assert "DRJIT_LIBLLVM_PATH" not in os.environ or os.environ["DRJIT_LIBLLVM_PATH"] != "/opt/llvm-21/lib/libLLVM.so.21.1"
    assert INSTALL_HINT in str(info.value) and "\n" not in str(info.value)

"""`saft info` lists the optional backends; the new commands' help and their one-line input errors."""

import importlib.metadata
import importlib.util
import subprocess
import sys

from saft.cli import main


def test_info_lists_backends(capsys):
    assert main(["info"]) == 0
    out = capsys.readouterr().out
    for name in ("Mitsuba 3:", "nvdiffrast:", "numba:", "CHOLMOD:", "Ray:", "viser:"):
        assert name in out
    for dist, name in (("ray", "Ray"), ("viser", "viser"), ("mitsuba", "Mitsuba 3")):
        if importlib.util.find_spec(dist) is not None:
            assert f"{name}:".ljust(12) + importlib.metadata.version(dist) in out
    if importlib.util.find_spec("mitsuba") is not None:
        assert "llvm_ad_rgb" in out


def test_view_and_batch_help_and_bad_input(tmp_path, capsys):
    for argv in (["view", "--help"], ["batch", "--help"]):
        r = subprocess.run([sys.executable, "-m", "saft", *argv], capture_output=True, text=True)
        assert r.returncode == 0 and "usage: saft" in r.stdout, r.stderr
    assert main(["view", str(tmp_path / "nothing")]) == 2
    assert main(["batch", str(tmp_path / "no-scene"), "--out", str(tmp_path / "b")]) == 2
    assert main(["batch", str(tmp_path), "--out", str(tmp_path / "b"), "--grid", "shape.epochs"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 3 and "nothing" in err[0] and "no-scene" in err[1] and "--grid" in err[2]

"""The tasks of `saft batch`: scenes × settings, where each one's result goes, and what is already done.

A setting is one combination of the `--grid key=v1,v2` values (the cartesian product over keys); its name,
which is also its folder, is "key=value" pairs joined by "," (e.g. `shape.lambda_force=0`). Without --grid
there is one setting, "", and results go straight to DIR/<scene>.

A finished task leaves DIR/<scene>[/<setting>]/batch.json (its command, status and wall seconds); a task that
stopped part-way leaves only the reconstruction's checkpoint/, and is run again with --resume.
"""

from __future__ import annotations

import itertools
import json
import re
from dataclasses import dataclass, field
from pathlib import Path

from saft.errors import SaftInputError
from saft.io_utils import atomic_write_json
from saft.reconstruct.checkpoint import checkpoint_path

MARKER = "batch.json"
LOG_DIR = "logs"
_UNSAFE = re.compile(r"[^A-Za-z0-9._=,+-]")


@dataclass(frozen=True)
class BatchTask:
    scene: Path                       # a native scene folder or a SAFT/PG-SfT scene .json
    scene_name: str                   # the column of the summary table
    setting: str                      # the row ("" without --grid)
    overrides: tuple[str, ...]        # --set values, then the setting's
    out_dir: Path
    options: dict = field(default_factory=dict, compare=False)   # gt, device, frames, root

    @property
    def label(self) -> str:
        return f"{self.scene_name}/{self.setting}" if self.setting else self.scene_name

    def command(self, python: str, resume: bool, threads: int = 0) -> list[str]:
        """The `saft reconstruct` command line of this task (`threads` > 0: torch's CPU threads, before the
        user's overrides, which win). Not --quiet: its log shows each phase's progress and ETA."""
        cmd = [python, "-m", "saft", "reconstruct", str(self.scene), "--out", str(self.out_dir)]
        if threads > 0:
            cmd += ["--set", f"run.threads={threads}"]
        for item in self.overrides:
            cmd += ["--set", item]
        if self.options.get("gt"):
            cmd.append("--gt")
        for key in ("device", "frames", "root"):
            if self.options.get(key) is not None:
                cmd += [f"--{key}", str(self.options[key])]
        return cmd + (["--resume"] if resume else [])

    def log_path(self, batch_dir: Path) -> Path:
        name = self.scene_name + (f"__{self.setting}" if self.setting else "")
        return Path(batch_dir) / LOG_DIR / f"{_UNSAFE.sub('_', name)}.log"


def _split_values(text: str) -> list[str]:
    """v1,v2,... split at commas outside brackets and quotes (so `[1, 2],[3, 4]` is two values)."""
    out, depth, quote, cur = [], 0, None, ""
    for ch in text:
        if quote:
            quote = None if ch == quote else quote
        elif ch in "\"'":
            quote = ch
        elif ch in "[{":
            depth += 1
        elif ch in "]}":
            depth -= 1
        elif ch == "," and depth == 0:
            out.append(cur.strip())
            cur = ""
            continue
        cur += ch
    out.append(cur.strip())
    return out


def parse_grid(items: list[str] | None) -> list[tuple[str, list[str]]]:
    """`--grid key=v1,v2` items → [(key, [v1, v2])]; bad items raise SaftInputError naming them."""
    grid = []
    for item in items or []:
        key, sep, values = item.partition("=")
        vals = _split_values(values) if sep else []
        if not key.strip() or not vals or any(v == "" for v in vals):
            raise SaftInputError("--grid", f"expected key=value1,value2,..., got {item!r}")
        if key.strip() in (k for k, _ in grid):
            raise SaftInputError("--grid", f"key {key.strip()!r} given twice")
        grid.append((key.strip(), vals))
    return grid


def settings(grid: list[tuple[str, list[str]]]) -> list[tuple[str, tuple[str, ...]]]:
    """(name, overrides) of every combination of the grid's values, in the order given; [("", ())] without one."""
    if not grid:
        return [("", ())]
    out = []
    for combo in itertools.product(*(vals for _, vals in grid)):
        pairs = [f"{key}={val}" for (key, _), val in zip(grid, combo)]
        out.append((_UNSAFE.sub("_", ",".join(pairs)), tuple(pairs)))
    return out


def scene_name(scene: Path) -> str:
    """R1 for .../scenes/R1.json, the folder's name for a native scene."""
    return scene.stem if scene.suffix.lower() == ".json" else scene.resolve().name


def plan_tasks(scenes: list[Path], out: Path, sets: list[str] | None = None,
               grid: list[tuple[str, list[str]]] | None = None, options: dict | None = None) -> list[BatchTask]:
    """Every scene × setting as a task writing to OUT/<scene>[/<setting>]."""
    if not scenes:
        raise SaftInputError("saft batch", "no scenes given")
    names: dict[str, Path] = {}
    for scene in scenes:
        if not scene.exists():
            raise SaftInputError(scene, "scene not found")
        name = scene_name(scene)
        if name in names and names[name].resolve() != scene.resolve():
            raise SaftInputError(scene, f"two scenes are named {name!r} ({names[name]}); their results would mix")
        names[name] = scene
    tasks = []
    for name, scene in names.items():
        for setting, extra in settings(grid or []):
            folder = out / _UNSAFE.sub("_", name) / setting if setting else out / _UNSAFE.sub("_", name)
            tasks.append(BatchTask(scene.resolve(), name, setting, tuple(sets or ()) + extra, folder.resolve(),
                                   dict(options or {})))
    return tasks


def read_marker(task: BatchTask) -> dict | None:
    path = task.out_dir / MARKER
    try:
        return json.loads(path.read_text()) if path.is_file() else None
    except json.JSONDecodeError:
        return None


def write_marker(task: BatchTask, record: dict) -> None:
    atomic_write_json(task.out_dir / MARKER, record)


def task_state(task: BatchTask) -> str:
    """"done" (finished by an earlier batch with the same overrides), "resume" (a checkpoint of an
    unfinished run), "conflict" (finished with other overrides: left alone) or "new"."""
    marker = read_marker(task)
    if marker is not None and marker.get("status") == "done":
        same = list(marker.get("overrides", [])) == list(task.overrides) and \
            bool(marker.get("gt")) >= bool(task.options.get("gt"))
        return "done" if same else "conflict"
    return "resume" if checkpoint_path(task.out_dir).is_file() else "new"

"""`saft batch`: scenes × settings as Ray tasks, each one `saft reconstruct` in a subprocess.

Ray is started on this machine (or joined, with an address) by the driver; each task asks for one CPU (one
GPU as well when the cluster has GPUs; `--resources` changes that) and runs `python -m saft reconstruct
SCENE --out DIR/<scene>[/<setting>] --quiet [--set ...] [--gt] [--resume]` with its output in
DIR/logs/<task>.log. The subprocess keeps a crashing run from taking the worker down. Tasks finished earlier
are skipped; tasks with a checkpoint resume (after Ctrl-C, the runs stop with their workers and resume from
their last periodic checkpoint, written at most run.checkpoint_seconds apart). A failed task
is reported with the last line of its log and does not stop the others. At the end DIR/summary.csv and
DIR/summary.html are written (saft.batch.summary).
"""

from __future__ import annotations

import logging
import os
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from saft.batch.plan import BatchTask, read_marker, task_state, write_marker
from saft.batch.summary import TaskOutcome, write_summary
from saft.errors import BackendUnavailableError, SaftInputError

log = logging.getLogger("saft")


@dataclass(frozen=True)
class TaskResources:
    num_cpus: float = 1.0
    num_gpus: float = 0.0
    custom: tuple[tuple[str, float], ...] = ()

    def ray_options(self) -> dict:
        opts = {"num_cpus": self.num_cpus, "num_gpus": self.num_gpus}
        if self.custom:
            opts["resources"] = dict(self.custom)
        return opts


def parse_resources(items: list[str] | None, cluster_has_gpu: bool) -> TaskResources:
    """`--resources CPU=2 GPU=0 my_tag=1` → what each task asks Ray for (default: 1 CPU, plus 1 GPU when the
    cluster has one)."""
    cpus, gpus, custom = 1.0, 1.0 if cluster_has_gpu else 0.0, []
    for item in items or []:
        for part in item.split(","):
            key, sep, val = part.partition("=")
            try:
                amount = float(val)
            except ValueError:
                amount = -1.0
            if not sep or not key.strip() or amount < 0:
                raise SaftInputError("--resources", f"expected NAME=AMOUNT (e.g. CPU=2, GPU=1), got {part!r}")
            key = key.strip()
            if key.upper() == "CPU":
                cpus = amount
            elif key.upper() == "GPU":
                gpus = amount
            else:
                custom.append((key, amount))
    if cpus <= 0:
        raise SaftInputError("--resources", "a task needs at least some CPU (CPU > 0)")
    return TaskResources(cpus, gpus, tuple(custom))


def _last_line(path: Path) -> str:
    try:
        lines = [ln.strip() for ln in path.read_text(errors="replace").splitlines() if ln.strip()]
    except OSError:
        return ""
    return lines[-1][:300] if lines else ""


def execute_task(task: BatchTask, batch_dir: str, threads: int) -> dict:
    """Run one task (inside a Ray worker): `saft reconstruct` in a subprocess, its output to the task's log.
    Returns {"status": "done" | "failed" | "interrupted" (the run exited with 130), "wall_s", "error", "resumed"}."""
    resume = task_state(task) == "resume"
    log_path = task.log_path(Path(batch_dir))
    log_path.parent.mkdir(parents=True, exist_ok=True)
    cmd = task.command(sys.executable, resume, max(1, threads))
    t0 = time.perf_counter()
    with open(log_path, "a") as fh:
        fh.write(f"$ {' '.join(cmd)}\n")
        fh.flush()
        rc = subprocess.run(cmd, stdout=fh, stderr=subprocess.STDOUT, env=dict(os.environ)).returncode
    wall = time.perf_counter() - t0
    if rc != 0:
        return {"status": "interrupted" if rc == 130 else "failed", "wall_s": wall, "resumed": resume,
                "error": f"exit {rc}: {_last_line(log_path)}"}
    record = {"status": "done", "wall_s": wall + float((read_marker(task) or {}).get("wall_s", 0.0)),
              "overrides": list(task.overrides), "gt": bool(task.options.get("gt")), "scene": str(task.scene),
              "setting": task.setting, "command": cmd}
    write_marker(task, record)
    return {"status": "done", "wall_s": wall, "error": "", "resumed": resume}


def _import_ray():
    try:
        import ray
    except ImportError as exc:
        raise BackendUnavailableError(f"saft batch needs Ray ({exc}); pip install 'ray>=2.9' "
                                      "(install.sh installs it)") from None
    return ray


def _init_ray(ray, address: str | None, num_cpus: int | None) -> None:
    kw = dict(include_dashboard=False, logging_level=logging.WARNING, log_to_driver=False)
    if address:
        ray.init(address=address, **kw)
    else:
        ray.init(num_cpus=num_cpus, num_gpus=None, **kw)


class _Display:
    """Live progress: one bar for the batch and a line per running task (its latest log line)."""

    def __init__(self, total: int, quiet: bool):
        from rich.console import Console
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

        self.console = Console(stderr=True)
        self.quiet = quiet or not self.console.is_terminal
        self.progress = None
        if not self.quiet:
            self.progress = Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(),
                                     TimeElapsedColumn(), TextColumn("{task.fields[info]}"), console=self.console)
            self.progress.start()
            self.overall = self.progress.add_task("[bold]batch", total=total, info="")
        self.rows: dict[str, int] = {}

    def start(self, task: BatchTask) -> None:
        if self.progress is not None:
            self.rows[task.label] = self.progress.add_task(f"  {task.label}", total=None, info="running")

    def info(self, task: BatchTask, text: str) -> None:
        if self.progress is not None and task.label in self.rows:
            self.progress.update(self.rows[task.label], info=text[-70:])

    def finish(self, task: BatchTask, outcome: TaskOutcome, done: int) -> None:
        line = (f"{outcome.status:<11} {task.label}  ({outcome.wall_s:.0f} s)"
                + (f"  {outcome.error}" if outcome.error else ""))
        if self.progress is not None:
            if task.label in self.rows:
                self.progress.remove_task(self.rows.pop(task.label))
            self.progress.update(self.overall, completed=done)
            self.progress.console.print(line)
        else:
            print(line, flush=True)

    def stop(self) -> None:
        if self.progress is not None:
            self.progress.stop()


def run_batch(tasks: list[BatchTask], batch_dir: str | Path, *, address: str | None = None,
              num_cpus: int | None = None, resources: list[str] | None = None,
              quiet: bool = False) -> list[TaskOutcome]:
    """Run every task not finished yet on Ray; write DIR/summary.csv and DIR/summary.html; return the
    outcome of every task (skipped ones included) in the order given."""
    batch_dir = Path(batch_dir).resolve()
    batch_dir.mkdir(parents=True, exist_ok=True)
    outcomes: dict[int, TaskOutcome] = {}
    todo = []
    for i, task in enumerate(tasks):
        state = task_state(task)
        if state == "done":
            wall = float((read_marker(task) or {}).get("wall_s", 0.0))
            outcomes[i] = TaskOutcome(task, "skipped", wall, "finished earlier")
        elif state == "conflict":
            outcomes[i] = TaskOutcome(task, "failed", 0.0, f"{task.out_dir / 'batch.json'} was made with other "
                                                        "--set/--grid values; remove the folder to run it again")
        else:
            todo.append(i)
    display = _Display(len(tasks), quiet)
    for i, o in outcomes.items():
        display.finish(o.task, o, len(outcomes))
    if todo:
        ray = _import_ray()
        _init_ray(ray, address, num_cpus)
        try:
            res = parse_resources(resources, ray.cluster_resources().get("GPU", 0) > 0)
            remote = ray.remote(execute_task).options(**res.ray_options(), max_retries=0)
            pending = {remote.remote(tasks[i], str(batch_dir), int(max(1, res.num_cpus))): i for i in todo}
            for i in todo:
                display.start(tasks[i])
            try:
                while pending:
                    ready, _ = ray.wait(list(pending), num_returns=1, timeout=1.0)
                    for ref in ready:
                        i = pending.pop(ref)
                        try:
                            r = ray.get(ref)
                            outcomes[i] = TaskOutcome(tasks[i], r["status"], r["wall_s"], r["error"], r["resumed"])
                        except Exception as exc:  # the worker itself died: report, keep the others going
                            outcomes[i] = TaskOutcome(tasks[i], "failed", 0.0, f"{type(exc).__name__}: "
                                                      f"{str(exc).strip().splitlines()[-1][:300]}")
                        display.finish(tasks[i], outcomes[i], len(outcomes))
                    for i in pending.values():
                        display.info(tasks[i], _last_line(tasks[i].log_path(batch_dir)))
            except KeyboardInterrupt:
                log.warning("interrupted: the running reconstructions stop too; the same command resumes them "
                            "from their last checkpoint")
                for ref, i in pending.items():
                    ray.cancel(ref, force=True)
                    outcomes[i] = TaskOutcome(tasks[i], "interrupted", 0.0, "interrupted; resumes on the next run")
                raise
            finally:
                display.stop()
                write_summary(batch_dir, [outcomes[i] for i in sorted(outcomes)])
        finally:
            ray.shutdown()
    else:
        display.stop()
        write_summary(batch_dir, [outcomes[i] for i in sorted(outcomes)])
    return [outcomes[i] for i in range(len(tasks))]

"""saft.batch — `saft batch SCENE... --out DIR`: many reconstructions (scenes × settings) as Ray tasks.

    plan_tasks(scenes, out, sets, grid, options) -> list[BatchTask]     what to run, and where
    run_batch(tasks, out, address=None, num_cpus=None, resources=None)   run on local Ray or a cluster;
        -> list[TaskOutcome]                                             writes DIR/summary.csv and .html

Modules: plan (tasks, settings from --grid, what is finished), run (Ray; ray is imported only there, when
something is to run), summary (summary.csv, summary.html).
"""

from saft.batch.plan import BatchTask, parse_grid, plan_tasks
from saft.batch.run import run_batch
from saft.batch.summary import TaskOutcome

__all__ = ["BatchTask", "TaskOutcome", "parse_grid", "plan_tasks", "run_batch"]

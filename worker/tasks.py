"""``worker.tasks.run_job``: the dotted name jobs were enqueued under before ``worker.jobs``.

RQ imports a job's function by the name stored with the job, so a job still waiting in a queue while
the workers are upgraded runs through this alias instead of failing to import (no accepted job is
lost).  New jobs are enqueued as ``fastmesh_jobs.states.TASK``.
"""

from .jobs import run_job

__all__ = ["run_job"]

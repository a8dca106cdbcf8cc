"""``drago study``: every method x seed on a task sequence, their transfer cases and one report, carried out
by a backend and continued after any crash by the same command.

The modules: :mod:`~drago.study.plan` works out the plan from what is on disk (no processes);
:mod:`~drago.study.local` runs it as child processes on this machine and :mod:`~drago.study.slurm` as SLURM
batch jobs; :mod:`~drago.study.report` writes the report (and the units' records) whichever backend ran the jobs.
"""

from __future__ import annotations

from drago.study.local import StudyResult, run_study
from drago.study.plan import (DEFAULT_METHODS, DEFAULT_PRESET, DEFAULT_SEEDS, Job, StudyError, StudyPlan,
                              describe_plan, parse_cases, parse_seeds, plan_study)
from drago.study.report import record_units, write_report

__all__ = ["DEFAULT_METHODS", "DEFAULT_PRESET", "DEFAULT_SEEDS", "Job", "StudyError", "StudyPlan", "StudyResult",
           "describe_plan", "parse_cases", "parse_seeds", "plan_study", "record_units", "run_study", "write_report"]

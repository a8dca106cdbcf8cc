"""A study's report, from what is on disk, whichever backend ran its jobs: the records of finished units
first (with a records folder), then the report over the runs and the transfers' tables in ``OUT/report``.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from drago.config import ConfigError
from drago.study.plan import StudyPlan, record_verdict
from drago.training.records import RecordError
from drago.training.rundir import RunDirError, is_complete, is_run_dir

__all__ = ["record_units", "write_report"]


def record_units(plan: StudyPlan, echo: Callable[[str], None] = print) -> list[Path]:
    """Record every finished unit of a study with a records folder whose record is missing or has another
    protocol (what a SLURM study's report job does before its report; the local backend records each unit as
    it finishes). Returns the records written.

    Raises:
        RecordError: a finished unit that cannot be recorded, or whose record lacks the study's protocol.
    """
    from drago.eval.unit import record_unit

    written = []
    for run in plan.runs:
        if run.record is None or run.recorded or record_verdict(run.record, run.protocol) is None:
            continue
        mine = [t for t in plan.transfers if (t.method, t.seed) == (run.method, run.seed)]
        if not all(is_complete(job.directory) for job in (run, *mine)):
            continue
        record_unit(run.directory, run.record)
        mismatch = record_verdict(run.record, run.protocol)
        if mismatch:
            raise RecordError(f"the record of {run.label} does not have the study's protocol: {mismatch}")
        echo(f"recorded {run.label}: {run.record}")
        written.append(run.record)
    return written


def _report_sources(plan: StudyPlan) -> list[Path]:
    """What the report reads of each unit: its record where it has one with the study's protocol, else its
    run directory (a unit not yet recorded); a record of another protocol is never mixed in."""
    sources = []
    for run in plan.runs:
        if run.record is not None and record_verdict(run.record, run.protocol) is None:
            sources.append(run.record)
        elif is_run_dir(run.directory):
            sources.append(run.directory)
    return sources


def write_report(plan: StudyPlan, echo: Callable[[str], None] = print) -> tuple[list[Path], str | None]:
    """The study's report from what is on disk (the end of a local study, ``drago study --report-only``, a SLURM
    study's last job), after recording its finished units where it has a records folder.

    Returns:
        The files written, and why none were (None when written).
    """
    from drago.report import build_report, write_transfer_tables
    from drago.report.runs import find_transfer_dirs, opened_runs
    from drago.training.checkpoint import CheckpointError

    try:
        if plan.records is not None:
            record_units(plan, echo)
        sources = _report_sources(plan)
        if not sources:
            return [], "no run of the study has started"
        paths = list(build_report(sources, plan.report_dir))
        with opened_runs(sources) as found:
            names = {case: (f"{shown}: {case.relative_to(view)}" if view != Path(shown) else str(case))
                     for view, shown in found for case in find_transfer_dirs(view)}
            paths += write_transfer_tables(list(names), plan.report_dir, names)
    except (RunDirError, ConfigError, CheckpointError) as err:
        echo(f"report not written: {err}")
        return [], str(err)
    for path in paths:
        echo(f"wrote {path}")
    return paths, None

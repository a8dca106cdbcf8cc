"""The public API: what ``import drago`` offers, and all that the command line uses.

``import drago`` itself stays fast: the package reaches these names on first use (PEP 562), so torch and
the trainer are loaded only when something needs them (docs: Extending drago). For example::

    import drago

    cfg = drago.load_config("smoke", ["env.tasks=[room1,room2]"], method="drago")
    run = drago.train(cfg, out="runs/demo")           # trains; returns a drago.Run
    print(run.tasks[-1]["final_eval_return"])
    rows = drago.coverage(run.path)                    # grid: world-model accuracy per room and stage
    drago.build_report([run.path], "reports/demo")
"""

from __future__ import annotations

from pathlib import Path

import drago.agent.factory  # noqa: F401 - registers the built-in agent kinds
from drago.agent.protocol import (AgentCapabilities, AgentKind, ContinualAgent, agent_kinds, get_agent_kind,
                                  register_agent_kind)
from drago.agent.protocol import plugin_problems as _agent_plugin_problems
from drago.agent.speed import resolve_speed, speed_summary
from drago.config import Config, ConfigError, MethodSetting, available_presets, describe_settings
from drago.settings_docs import describe_all as describe_settings_fully
from drago.config import load_config as _load_settings
from drago.continual import ContinualMethod, TaskState, available_methods, check_method, methods
from drago.continual import plugin_problems as _method_plugin_problems
from drago.continual.registry import RegistryError, register_method
from drago.envs import (
    Domain,
    DomainError,
    available_domains,
    get_domain,
    gym_domain,
    register_domain,
    task_descriptions,
)
from drago.envs import plugin_problems as _domain_plugin_problems
from drago.plugins import PluginProblem
from drago.eval.coverage import COVERAGE_FILE, write_coverage_csv
from drago.eval.coverage import coverage_of_run as coverage
from drago.eval.coverage import format_table as format_coverage_table
from drago.eval.coverage import run_checkpoints as coverage_checkpoints
from drago.eval.components import components_checkpoints, components_of_run, evaluate_components
from drago.eval.costs import costs_of_run
from drago.eval.heldout import RETENTION_FILE, retention_matrix, write_retention_csv
from drago.eval.reviewer_pay import StagePay, reviewer_pay_of_run
from drago.eval.zero_shot import ZERO_SHOT_FILE, ZeroShotError, write_zero_shot_csv, zero_shot_matrix
from drago.eval.zero_shot import ceiling as zero_shot_ceiling
from drago.eval.zero_shot import format_table as format_zero_shot_table
from drago.eval.zero_shot import matrix_metrics as zero_shot_metrics
from drago.eval.zero_shot import run_checkpoints as zero_shot_checkpoints
from drago.eval.heldout import format_table as format_retention_table
from drago.eval.heldout import heldout_checkpoints as retention_checkpoints
from drago.eval.predictor import WorldModelPredictor, load_world_model
from drago.report import ReportError, build_report
from drago.study.command import SLURM_OPTIONS, StudyOutcome, study_command
from drago.training.checkpoint import CheckpointError, NonFiniteCheckpoint
from drago.training.run import (Interrupted, continue_with, default_run_dir, new_run, new_transfer, resume,
                               run_paper_cases, run_transfer)
from drago.training.records import RECORD_SUFFIX, RecordError, read_record
from drago.training.rundir import RunDirError, read_run_config
from drago.training.runs import Record, Run
from drago.training.trainer import Trainer, TrainingDiverged

__all__ = [
    "COVERAGE_FILE", "RETENTION_FILE", "NonFiniteCheckpoint", "TrainingDiverged", "coverage_checkpoints",
    "format_coverage_table", "format_retention_table", "retention_checkpoints", "write_coverage_csv",
    "write_retention_csv", "ZERO_SHOT_FILE", "ZeroShotError", "format_zero_shot_table", "write_zero_shot_csv",
    "zero_shot_ceiling", "zero_shot_checkpoints", "zero_shot_matrix", "zero_shot_metrics", "StagePay",
    "reviewer_pay_of_run", "plugin_packages", "describe_settings_fully", "MethodSetting",
    "RECORD_SUFFIX", "RecordError", "read_record", "record_run", "recorded_evaluation", "components_checkpoints",
    "components_of_run", "costs_of_run", "evaluate_components", "AgentCapabilities", "AgentKind", "ContinualAgent",
    "agent_kinds", "get_agent_kind", "register_agent_kind",
    "CheckpointError", "Config", "ConfigError", "ContinualMethod", "Domain", "DomainError", "PluginProblem",
    "Record", "RegistryError", "ReportError", "Run", "RunDirError", "TaskState", "Trainer", "WorldModelPredictor",
    "available_domains", "available_methods", "available_presets", "build_report", "coverage", "default_run_dir",
    "describe_settings", "get_domain", "gym_domain", "load_config", "load_world_model", "methods", "new_run",
    "new_transfer", "plugin_problems", "register_domain", "register_method", "resume", "retention_matrix",
    "resolve_speed", "run_paper_cases", "run_transfer", "speed_summary", "task_descriptions", "train",
    "SLURM_OPTIONS", "StudyOutcome", "study_command", "Interrupted", "continue_with",
]


def load_config(preset: str, overrides: list[str] | None = None, method: str | None = None,
                seed: int | None = None, smoke: bool = False, inapplicable_ok: bool = False) -> Config:
    """A validated run config: a preset plus ``key=value`` overrides, with a method that exists.

    Args:
        preset: a packaged preset's name (``drago list`` shows them) or the path of a YAML file of the same
            form, whose ``base:`` may name a packaged preset.
        overrides: strings ``section.key=value``, or ``key=value`` for a key unique across sections.
        method: shortcut for ``method.name=...``.
        seed: shortcut for ``train.seed=...``.
        smoke: the preset's smoke path, a run of seconds through the same code (see
            :func:`drago.config.load_config`).
        inapplicable_ok: accept overrides that the chosen agent kind or method does not read (one list of
            overrides for several methods); by default such an override is an error naming who reads it.

    Raises:
        ConfigError: one line naming the bad preset, file and line, key, value or method.
    """
    return check_method(_load_settings(preset, overrides, method=method, seed=seed, smoke=smoke,
                                       inapplicable_ok=inapplicable_ok))


def plugin_problems() -> list[PluginProblem]:
    """Every plug-in (method, domain, agent kind or preset) that failed to load and was skipped; ``str(problem)``
    is one line."""
    from drago.config import preset_plugin_problems

    return [*_method_plugin_problems(), *_domain_plugin_problems(), *_agent_plugin_problems(),
            *preset_plugin_problems()]


def plugin_packages() -> dict[str, dict[str, str]]:
    """The package each plug-in came from: ``{"presets" | "methods" | "domains": {name: package}}``."""
    from drago.config import plugin_presets
    from drago.continual.registry import METHOD_PACKAGES, methods as _methods
    from drago.envs.registry import source_of

    _methods()  # loads the method plug-ins
    domains = {}
    for name in available_domains():
        source = source_of(name) or ""
        if source.startswith("entry point") and "of package '" in source:
            domains[name] = source.rsplit("of package '", 1)[1].rstrip("'")
    return {"presets": {name: package for name, (_, package) in plugin_presets().items()},
            "methods": dict(METHOD_PACKAGES), "domains": domains}


def train(cfg: Config, out: str | Path | None = None, force: bool = False, progress: bool = True) -> Run:
    """Train the config's task sequence into ``out`` (default ``runs/PRESET/METHOD/seedS``) and return the run.

    An existing run directory is refused unless ``force``; continue an interrupted one with
    :func:`resume` (``resume(path).run()``).

    Raises:
        RunDirError: an existing run directory; ConfigError: a bad config (a value of the wrong type or out of
            range, checked before anything is written).
    """
    from drago.config import validate

    validate(cfg)  # a config changed in Python since load_config is held to the same rules
    run_dir = Path(out) if out is not None else default_run_dir(cfg)
    trainer = new_run(check_method(cfg), run_dir, force=force, progress=progress)
    try:
        trainer.run()
    finally:
        trainer.logger.close()
    return Run(run_dir)


def recorded_evaluation(record: str | Path, filename: str) -> list[dict]:
    """The rows of an evaluation file a record holds (``coverage.csv``, ``zero_shot.csv``, ``retention.csv``,
    ...), numbers as numbers; empty when the record has no such file.

    Raises:
        RecordError: a corrupt record or one of another format version (one line).
    """
    import csv
    import io

    def value(text: str):
        for kind in (int, float):
            try:
                return kind(text)
            except ValueError:
                pass
        return text

    text = read_record(record)["files"].get(filename)
    return [] if text is None else [{k: value(v) for k, v in row.items()} for row in csv.DictReader(io.StringIO(text))]


def record_run(run_dir: str | Path, out: str | Path | None = None) -> tuple[Path, dict]:
    """Evaluate a finished run from its checkpoints and write its record (``drago record``).

    Args:
        run_dir: A run whose every task and transfer case has finished.
        out: The record file (default ``records/PRESET/METHOD/seedS.json.gz``).

    Returns:
        The record's path and contents.

    Raises:
        RecordError: an unfinished run or transfer, or a file that cannot be read (one line).
    """
    from drago.eval.unit import record_unit
    from drago.training.records import RECORD_SUFFIX

    if out is None:
        cfg = read_run_config(Path(run_dir))
        out = Path("records") / cfg.preset / cfg.method.name / f"seed{cfg.train.seed}{RECORD_SUFFIX}"
    return Path(out), record_unit(run_dir, out)


def __dir__() -> list[str]:
    return sorted(__all__)

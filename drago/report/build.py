"""Building a report from run directories: read, compute, render, write."""

from __future__ import annotations

from collections.abc import Iterable
from datetime import datetime
from pathlib import Path

from drago.envs import exact_world
from drago.report.components import components_section
from drago.report.content import Figure, Findings, Notes, Section
from drago.report.figures import CURVES_PNG, HEATMAP_PNG, TRANSFER_PNG, curves_png, heatmap_figure, transfer_png
from drago.report.render import REPORT_HTML, REPORT_MD, render_html, render_markdown
from drago.report.runs import (ReportedRun, ReportError, find_transfer_dirs, label_runs, opened_runs, read_run,
                               task_order)
from drago.report.tables import (
    coverage_matrix,
    coverage_rows,
    coverage_table,
    find_gaps,
    forward_transfer_table,
    metrics_table,
    retention_rows,
    retention_score_matrix,
    retention_tables,
    returns_table,
    runs_table,
)
from drago.report.paper import paper_tables, paper_training_table
from drago.report.reviewer_pay import (
    REVIEWER_PAY_PNG,
    REVIEWER_REWARD_PNG,
    reviewer_pay_section,
    reviewer_reward_figure,
)
from drago.report.visitation import VISITATION_PNG, visitation_section
from drago.report.zero_shot import zero_shot_matrix_of, zero_shot_rows, zero_shot_table
from drago.report.transfers import relearning_metrics, training_table, transfer_block, transfer_gaps, transfer_tables
from drago.training.records import is_record_view, record_view_meta
from drago.training.rundir import CONFIG_FILE, TRANSFER_FOLDER


def build_report(run_dirs: Iterable[str | Path], out_dir: str | Path) -> tuple[Path, Path]:
    """Write ``report.html`` (self-contained) and ``report.md`` (with PNG figures) for ``run_dirs``.

    Args:
        run_dirs: Run directories, folders holding run directories (see :func:`find_run_dirs`), records
            (``*.json.gz``) or folders holding records. Any mix of methods and seeds, finished or not. The
            transfer runs each run holds (``RUN_DIR/transfer/*``) are reported too; a transfer run given
            directly is one of them, never a continual run of its method.
        out_dir: Output folder, created if needed; nothing is written anywhere else.

    Returns:
        ``(html_path, md_path)``.

    Raises:
        ReportError: A path without runs, or an unreadable run file (one-line message).
        drago.training.records.RecordError: A corrupt record, or one of another format version.
        drago.config.ConfigError: An invalid ``config.yaml``.
        drago.training.checkpoint.CheckpointError: A corrupt checkpoint.
    """
    with opened_runs(run_dirs) as found:
        return _build_report(found, out_dir)


def _label_transfers(transfers: list[ReportedRun], source_of: dict[Path, ReportedRun]) -> dict[str, list[ReportedRun]]:
    """Group transfers as :func:`label_runs` does, each under its source run's label where the report split that
    run's method by a setting, so that a method is named the same in every table; a setting in which the
    transfers themselves differ follows in brackets of its own."""
    label_runs(transfers)
    groups: dict[str, list[ReportedRun]] = {}
    for transfer in transfers:
        source = source_of.get(transfer.path)
        if source is not None and source.label != source.method:
            own = transfer.label[len(transfer.method):].strip()
            transfer.label = f"{source.label} {own}" if own else source.label
        groups.setdefault(transfer.label, []).append(transfer)
    return groups


def _build_report(found: list[tuple[Path, str]], out_dir: str | Path) -> tuple[Path, Path]:
    given = [read_run(path, shown) for path, shown in found]
    runs = [run for run in given if not run.is_transfer]
    transfers = [run for run in given if run.is_transfer]
    findings = Findings()
    seen = {run.path.resolve() for run in given}
    source_of: dict[Path, ReportedRun] = {}  # a transfer found in a run's folder -> that run
    for run in runs:
        for path in find_transfer_dirs(run.path):
            if path.resolve() in seen:
                continue
            seen.add(path.resolve())
            shown = str(path) if run.shown == str(run.path) else f"{run.shown}: {TRANSFER_FOLDER}/{path.name}"
            transfer = read_run(path, shown)
            if transfer.is_transfer:
                transfers.append(transfer)
                source_of[transfer.path] = run
            else:
                findings.missing.append(f"{shown}: not a transfer run (no transfer.checkpoint in its "
                                        f"{CONFIG_FILE}); left out")
    groups = label_runs(runs)
    found_groups = _label_transfers(transfers, source_of)
    tgroups = {label: found_groups[label] for label in dict.fromkeys([*groups, *found_groups]) if label in found_groups}
    colours = {label: f"C{i % 10}" for i, label in enumerate(dict.fromkeys([*groups, *tgroups]))}
    tasks = task_order(runs)
    coverage = {run.path: coverage_rows(run, findings) for run in runs}

    sections: list[Section] = [runs_table(groups), returns_table(groups, tasks), *paper_training_table(groups, tasks)]
    curves = curves_png(groups, tasks, colours)
    if curves is not None:
        sections.append(Figure("curves", "Learning curves", "Evaluation return during each task, as a fraction of "
                               "the DP optimum (grid) or raw return (DeepMind Control, no known optimum), against "
                               "the task's env steps (learner plus reviewer; when a reviewer spent any, the top "
                               "row is against the learner's env steps alone): the mean over seeds with its 95% "
                               "bootstrap CI as a band (no band for a single seed).", curves, CURVES_PNG))
    sections += forward_transfer_table(groups, tasks, findings)
    if any(exact_world(run.cfg.env.domain) for run in runs):
        matrices = {run.path: coverage_matrix(run, coverage[run.path], findings) for run in runs}
        sections += [coverage_table(groups, coverage),
                     metrics_table(groups, matrices, "metrics", "Continual-learning metrics (from coverage)",
                                    "coverage accuracy in the room of task j")]
        zero_shot = {run.path: zero_shot_rows(run, findings) for run in runs}
        table = zero_shot_table(groups, zero_shot)
        if table is not None:
            sections += [table, metrics_table(
                groups, {run.path: zero_shot_matrix_of(run, zero_shot[run.path]) for run in runs},
                "zero-shot-metrics", "Continual-learning metrics (from zero-shot planning)",
                "the zero-shot return on task j as a fraction of its DP optimum")]
    retention = {run.path: retention_rows(run, findings) for run in runs}  # DeepMind Control runs only
    if any(retention.values()):
        sections += retention_tables(groups, retention)
        matrices = {path: retention_score_matrix(rows) for path, rows in retention.items()}
        sections.append(metrics_table(
            groups, matrices, "retention-metrics", "Continual-learning metrics (from held-out retention)",
            "the world model's prediction score −log(MSE + ε) on the held-out transitions of task j"))
    heatmap = heatmap_figure(groups)
    if heatmap is not None:
        sections.append(Figure("heatmap", "World-model prediction score", "Per-cell prediction score of the "
                               "world model after each stage (rows: methods, columns: stages), the mean of "
                               "−log(MSE + ε) over the cell's 4 headings × 3 actions, averaged over seeds; "
                               "light = well predicted, one colour scale for all panels, walls and blocks "
                               "grey. The stage's task start (○) and goal (★) are marked; a red × is a cell "
                               "with a non-finite prediction.", heatmap, HEATMAP_PNG))
    sections += components_section(groups, findings)
    sections += visitation_section(groups)
    sections += reviewer_pay_section(groups)
    reviewer_reward = reviewer_reward_figure(groups, colours)
    if reviewer_reward is not None:
        sections.append(reviewer_reward)
    if transfers:
        cases = sorted({run.case for run in transfers})
        blocks = {run.path: transfer_block(run) for run in transfers}
        sections += transfer_tables(tgroups, cases, blocks)
        sections += paper_tables(tgroups, cases, {str(path): (block or {}).get("few_shot", {}).get("equal_episodes") or {}
                                                  for path, block in blocks.items()})
        sections.append(training_table(tgroups, cases))
        sections += relearning_metrics(groups, transfers, blocks, findings)
        transfer_curves = transfer_png(tgroups, cases, colours)
        if transfer_curves is not None:
            sections.append(Figure("transfer-curves", "Transfer learning curves", "Evaluation return on each test "
                                   "case (columns) as a fraction of the DP optimum (grid) or raw return (DeepMind "
                                   "Control), against the learner's env steps (top) and the total env steps, "
                                   "learner plus reviewer (bottom): the mean over seeds with its 95% bootstrap CI "
                                   "as a band (no band for a single seed).", transfer_curves, TRANSFER_PNG))
        transfer_gaps(groups, tgroups, cases, blocks, findings)
    find_gaps(groups, tasks, findings)
    sections.append(Notes("missing", "Missing", "What these runs do not (yet) provide.",
                          findings.missing or ["Nothing: every run finished every task of its sequence, "
                                               "and every method has the same number of seeds."]))
    if findings.notes:
        sections.append(Notes("notes", "Notes", "How the numbers above were obtained.", findings.notes))

    seeds = ", ".join(f"{label}: {len(r)} run{'s' if len(r) != 1 else ''}" for label, r in groups.items())
    recorded = [record_view_meta(run.path).get("provenance") or {} for run in runs if is_record_view(run.path)]
    if recorded and len(recorded) == len(runs):
        # Built from records alone: the same records give the same page, wherever and whenever it is built.
        latest = max(recorded, key=lambda p: str(p.get("recorded")))
        meta = (f"Built from {len(runs)} records ({seeds}), the latest recorded {latest.get('recorded', '?')} "
                f"by drago {latest.get('drago', '?')} at commit {str(latest.get('commit') or 'unknown')[:12]}")
    else:
        meta = (f"Generated {datetime.now().strftime('%Y-%m-%d %H:%M')} from {len(runs)} run directories "
                f"({seeds or 'none'})")
    meta += f" and {len(transfers)} transfer run{'s' * (len(transfers) != 1)}." if transfers else "."
    title = "DRAGO report"
    out = Path(out_dir)
    html_path, md_path = out / REPORT_HTML, out / REPORT_MD
    try:
        out.mkdir(parents=True, exist_ok=True)
        for figure_file in (CURVES_PNG, HEATMAP_PNG, TRANSFER_PNG, VISITATION_PNG, REVIEWER_PAY_PNG,
                            REVIEWER_REWARD_PNG):
            (out / figure_file).unlink(missing_ok=True)  # a figure from an earlier report must not linger
        for section in sections:
            if isinstance(section, Figure):
                (out / section.filename).write_bytes(section.png)
        html_path.write_text(render_html(title, meta, sections), encoding="utf-8")
        md_path.write_text(render_markdown(title, meta, sections), encoding="utf-8")
    except OSError as err:
        raise ReportError(f"cannot write the report into {out} ({err.strerror or err})") from None
    return html_path, md_path

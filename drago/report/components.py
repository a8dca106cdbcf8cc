"""The report's "Which part forgot" section: per-component retention, the swap test, and what each method
stores and spends, read from the files each unit records (docs: Evaluation, "Which part forgot")."""

from __future__ import annotations

import csv
import io
import math
from pathlib import Path
from typing import Any

import numpy as np

from drago.eval.components import COMPONENTS, COMPONENTS_FILE, SWAP_FILE
from drago.eval.costs import BYTE_KINDS, read_costs
from drago.report.content import Figure, Findings, Table
from drago.report.runs import ReportedRun, as_number
from drago.report.tables import format_summary

__all__ = ["COMPONENTS_PNG", "components_section"]

COMPONENTS_PNG = "components.png"
#: How each measure reads, for the table and the figure: higher is better for all but the errors.
LABELS = {"dynamics_1step": "dynamics, 1 step (exact)", "dynamics_hstep": "dynamics, H steps (exact)",
          "reward_error": "reward error (MAE)", "value_error": "value error (MAE / mean |Q*|)",
          "value_order": "value order (rank corr. with Q*)",
          "policy_agreement": "policy = optimal action", "return_own_heads": "return, model + own heads",
          "return_true_reward": "return, model + true reward"}
ERRORS = ("reward_error", "value_error")


def _read_rows(path: Path) -> list[dict[str, str]] | None:
    try:
        with path.open(newline="") as handle:
            return list(csv.DictReader(handle))
    except OSError:
        return None


def _gather(groups: dict[str, list[ReportedRun]], findings: Findings):
    """Per method: component values {(component, task, stage): [seed values]}, swap rows and cost rows."""
    values: dict[str, dict[tuple[str, str, int], list[float]]] = {}
    swaps: dict[str, list[dict[str, str]]] = {}
    costs: dict[str, list[list[dict[str, Any]]]] = {}
    lacking = []
    for label, runs in groups.items():
        for run in runs:
            rows = _read_rows(run.path / COMPONENTS_FILE)
            if rows is None:
                if run.finished:
                    lacking.append(run.shown)
                continue
            mine = values.setdefault(label, {})
            for row in rows:
                value = as_number(row["value"])
                if math.isfinite(value):
                    mine.setdefault((row["component"], row["task"], int(row["stage"])), []).append(value)
            zero_shot = _read_rows(run.path / "zero_shot.csv") or []
            for row in zero_shot:
                if row.get("task") in {task for _, task, _ in mine} and row.get("fraction") not in (None, ""):
                    mine.setdefault(("return_true_reward", row["task"], int(row["stage"])), []).append(
                        as_number(row["fraction"]))
            swaps.setdefault(label, []).extend(_read_rows(run.path / SWAP_FILE) or [])
            spent = read_costs(run.path)
            if spent:
                costs.setdefault(label, []).append(spent)
    if lacking:
        findings.missing.append(f"{len(lacking)} run{'s' * (len(lacking) != 1)} without component measures "
                                f"(first: {lacking[0]}); `drago eval components RUN_DIR` makes them from the "
                                "checkpoints, and every study unit records them")
    return values, swaps, costs


def _component_table(values: dict[str, dict[tuple[str, str, int], list[float]]]) -> Table:
    rows = []
    for label, mine in values.items():
        tasks = list(dict.fromkeys(task for _, task, _ in sorted(mine, key=lambda key: key[2])))
        last = max(stage for _, _, stage in mine)
        for component in (*COMPONENTS, "return_true_reward"):
            for k, task in enumerate(tasks, start=1):
                own, final = mine.get((component, task, k)), mine.get((component, task, last))
                if own is None or final is None or k == last:
                    continue
                rows.append((label, LABELS[component], task, format_summary(own)[0], f"{last}",
                             format_summary(final)[0]))
    return Table("components", "Which part forgot: each part of the agent on earlier tasks",
                 "For every earlier task k, each part of the agent measured on task k's frozen probe (every "
                 "state and action of its room) right after task k and after the last stage: the world model's "
                 "one- and H-step exact-match accuracy, task k's reward and value heads against its true reward "
                 "and DP values, its policy head against the optimal actions, and the return of planning with "
                 "the model and task k's own heads, or with the model and the true reward (the zero-shot "
                 "matrix), as fractions of the DP optimum. Mean ± std [95% CI] over seeds.",
                 ("method", "part", "task", "after its task", "after stage", "then"), rows)


def _swap_table(swaps: dict[str, list[dict[str, str]]]) -> Table | None:
    rows = []
    for label, found in swaps.items():
        cases = list(dict.fromkeys((int(r["stage"]), r["task"]) for r in found))
        for stage, task in cases:
            mine = [r for r in found if (int(r["stage"]), r["task"]) == (stage, task)]

            def share(key: str, mine=mine) -> list[float]:
                return [as_number(r[key]) / as_number(r["optimum"]) for r in mine if r.get(key) not in (None, "")]

            saved, moved, refit, true = share("saved"), share("moved"), share("refit"), share("true_reward")
            lost = [s - m for s, m in zip(saved, moved)]
            recovered = [r - m for r, m in zip(refit, moved)]
            lowest, highest = share("refit_min"), share("refit_max")  # absent from a single-refit evaluation
            spread = f"{min(lowest):.2f}–{max(highest):.2f}" if lowest and highest else "–"
            rows.append((label, task, str(stage), str(len(mine)), *(format_summary(v)[0] for v in
                                                                     (saved, moved, refit)), spread,
                         *(format_summary(v)[0] for v in (true, lost, recovered))))
    if not rows:
        return None
    return Table("swap-test", "The swap test: did the model or the heads forget?",
                 "Return on an earlier task k after stage N, as a fraction of its DP optimum, planning with: the "
                 "model and heads saved after k (saved); the model after N under the heads saved after k (moved); "
                 "the model after N with k's heads refit on k's probe for a fixed budget that cannot change the "
                 "model (refit: the mean of several refits with their own seeds; refit range: the lowest and "
                 "highest single refit over all seeds, since one refit tends to reach the goal or not); the model "
                 "after N with the true reward (zero-shot). saved − moved is the whole loss; refit − moved what "
                 "re-attaching the heads recovers, knowledge the model still held; what the refit leaves is the "
                 "model's own forgetting. Mean ± std [95% CI] over seeds.",
                 ("method", "task k", "after stage N", "seeds", "saved", "moved", "refit", "refit range",
                  "zero-shot", "lost (saved − moved)", "recovered (refit − moved)"), rows)


def _mb(n: float) -> str:
    return f"{n / 1e6:.2f}"


def _carried_text(carried: dict[str, float], per_run: list[list[dict[str, Any]]]) -> str:
    """The carried kinds with their MB; a generator no task of any run updated is marked, since it is carried
    without anything learned in it (``drago-no-rehearsal`` builds DRAGO's generator and never trains it)."""
    idle_generator = all(row.get("vae_updates") == 0 for rows in per_run for row in rows)
    return ", ".join(f"{kind.replace('_', ' ')} {_mb(carried[kind])}"
                     + (" (never trained)" if kind == "generator" and idle_generator else "")
                     for kind in BYTE_KINDS if carried[kind])


def _cost_table(groups: dict[str, list[ReportedRun]], costs: dict[str, list[list[dict[str, Any]]]],
                values: dict[str, dict[tuple[str, str, int], list[float]]]) -> Table | None:
    rows = []
    for label, per_run in costs.items():
        last = [run_rows[-1] for run_rows in per_run]
        carried = {kind: float(np.mean([r[f"bytes_{kind}"] for r in last])) for kind in BYTE_KINDS}
        total_mb = sum(carried.values()) / 1e6
        steps = [sum(r["learner_env_steps"] for r in rows_) for rows_ in per_run]
        reviewer = [sum(r["reviewer_env_steps"] for r in rows_) for rows_ in per_run]
        updates = [sum(r["learner_updates"] + r["reviewer_updates"] for r in rows_) for rows_ in per_run]
        cpu_h = [sum(r["cpu_s"] or 0.0 for r in rows_) / 3600 for rows_ in per_run]
        kept = _old_task_retention(values.get(label, {}))
        per_mb = [k / total_mb for k in kept] if total_mb else []
        per_cpu = [k / c for k, c in zip(kept, cpu_h) if c] if kept else []
        kinds = _carried_text(carried, per_run)
        rows.append((label, kinds or "–", f"{total_mb:.2f}", "yes" if any(r["raw_data"] for r in last) else "no",
                     f"{np.mean(steps):,.0f}", f"{np.mean(reviewer):,.0f}", f"{np.mean(updates):,.0f}",
                     format_summary(cpu_h)[0], format_summary(kept)[0], format_summary(per_mb)[0],
                     format_summary(per_cpu)[0]))
    if not rows:
        return None
    return Table("costs", "What each method stores and spends",
                 "What a run carries into its next task (MB by kind after its last task: the world model, a "
                 "generator (marked where the run never trained it), a Fisher diagonal and anchor weights, raw "
                 "transitions of earlier tasks), whether that "
                 "includes raw data, the env steps of its learner and reviewer and its gradient updates over the "
                 "whole sequence (means over seeds), its CPU hours, and its retention: the mean one-step dynamics "
                 "accuracy on the earlier tasks' probes after the last stage, also per MB carried and per "
                 "CPU hour. Mean ± std [95% CI] over seeds where given.",
                 ("method", "carried (MB)", "total MB", "raw data", "learner env steps", "reviewer env steps",
                  "updates", "CPU hours", "retention", "retention per MB", "retention per CPU hour"), rows)


def _old_task_retention(mine: dict[tuple[str, str, int], list[float]]) -> list[float]:
    """Per seed: the mean one-step dynamics accuracy, after the last stage, on the tasks learned before it."""
    if not mine:
        return []
    last = max(stage for _, _, stage in mine)
    learned: dict[str, int] = {}
    for component, task, stage in mine:
        if component == "dynamics_1step":
            learned[task] = min(learned.get(task, stage), stage)
    per_task = [mine[("dynamics_1step", task, last)] for task, stage in learned.items()
                if stage < last and ("dynamics_1step", task, last) in mine]
    if not per_task:
        return []
    return [float(np.mean([values[i] for values in per_task])) for i in range(min(map(len, per_task)))]


def _figure(values: dict[str, dict[tuple[str, str, int], list[float]]]) -> bytes | None:
    """Rows: methods; columns: parts; each panel the task x stage matrix of the mean over seeds."""
    if not values:
        return None
    from matplotlib.figure import Figure as MplFigure

    parts = [c for c in (*COMPONENTS, "return_true_reward") if any(key[0] == c for m in values.values() for key in m)]
    methods = list(values)
    fig = MplFigure(figsize=(1.2 + 2.0 * len(parts), 0.8 + 2.0 * len(methods)), layout="constrained")
    axes = fig.subplots(len(methods), len(parts), squeeze=False)
    for row, method in enumerate(methods):
        mine = values[method]
        tasks = list(dict.fromkeys(task for _, task, _ in sorted(mine, key=lambda key: key[2])))
        stages = sorted({stage for _, _, stage in mine})
        for col, part in enumerate(parts):
            ax = axes[row][col]
            grid = np.full((len(tasks), len(stages)), np.nan)
            for i, task in enumerate(tasks):
                for j, stage in enumerate(stages):
                    if (part, task, stage) in mine:
                        grid[i, j] = float(np.mean(mine[(part, task, stage)]))
            error = part in ERRORS
            high = 1.0 if not error else max(1e-9, float(np.nanmax(grid)) if np.isfinite(grid).any() else 1.0)
            ax.imshow(grid, cmap="viridis_r" if error else "viridis", vmin=0.0, vmax=high, aspect="auto")
            for i in range(len(tasks)):
                for j in range(len(stages)):
                    if np.isfinite(grid[i, j]):
                        ax.text(j, i, f"{grid[i, j]:.2f}", ha="center", va="center", fontsize=7,
                                color="white" if (grid[i, j] / high < 0.5) != error else "black")
            ax.set_xticks(range(len(stages)), [str(s) for s in stages], fontsize=7)
            ax.set_yticks(range(len(tasks)), tasks, fontsize=7)
            if row == 0:
                ax.set_title(LABELS[part], fontsize=8)
            if col == 0:
                ax.set_ylabel(f"{method}\ntask", fontsize=9)
            if row == len(methods) - 1:
                ax.set_xlabel("after stage", fontsize=8)
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=80)
    return buffer.getvalue()


def components_section(groups: dict[str, list[ReportedRun]], findings: Findings) -> list[Table | Figure]:
    """The section's tables and figure, for the runs that recorded component measures (grid runs)."""
    values, swaps, costs = _gather(groups, findings)
    out: list[Table | Figure] = []
    if values:
        out.append(_component_table(values))
        png = _figure(values)
        if png is not None:
            out.append(Figure("components-figure", "Which part forgot, task × stage",
                              "Each part of the agent (columns) on each task's probe (rows of a panel) after each "
                              "stage (columns of a panel), one row of panels per method, mean over seeds; for the "
                              "errors darker is worse, for the others lighter is better.", png, COMPONENTS_PNG))
    swap = _swap_table(swaps)
    if swap is not None:
        out.append(swap)
    cost = _cost_table(groups, costs, values)
    if cost is not None:
        out.append(cost)
    return out

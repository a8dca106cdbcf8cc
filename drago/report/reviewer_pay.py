"""The report's "what the reviewer is paid" section (grid runs of the DRAGO methods that pay a reviewer): per
method and stage, θ, the share of each earlier task's room where the old-model term pays, and the mean intrinsic
reward per room, with maps of that reward on the grid; and, for any domain, what the reviewer earned during
each task, episode by episode, from ``train.csv`` (docs: Evaluation, where the reviewer goes)."""

from __future__ import annotations

import csv
import math


from drago.eval.coverage import ALL, GROUPS, CoverageError
from drago.eval.reviewer_pay import PAID
from drago.eval.unit import PaySummary, read_reviewer_pay
from drago.report.content import Figure, Table
from drago.report.figures import Panel, panels_png
from drago.report.runs import ReportedRun, as_number
from drago.report.tables import format_summary
from drago.training.runs import LOG_FILES

__all__ = ["REVIEWER_PAY_PNG", "REVIEWER_REWARD_PNG", "reviewer_pay_section", "reviewer_reward_figure"]

REVIEWER_PAY_PNG = "reviewer-pay.png"
REVIEWER_REWARD_PNG = "reviewer-reward.png"
# train.csv's per-episode sums of the reviewer's reward and its two terms, and θ's running estimate.
REWARD_ROWS = (("old_model_episode_reward", "Σ r_old per reviewer episode"),
               ("learner_model_episode_cost", "Σ c per reviewer episode"),
               ("reviewer_episode_reward", "Σ r = Σ (r_old − α·c)"),
               ("threshold", "θ estimated for the next task"))
ROOMS = tuple(group for group in GROUPS if group != ALL)
PAY_LABEL = "reviewer's reward r_old − α·c at the task's start\nmean over 4 headings × 3 actions"


def _pays(groups: dict[str, list[ReportedRun]]) -> dict[str, list[list[PaySummary]]]:
    found: dict[str, list[list[PaySummary]]] = {}
    for label, runs in groups.items():
        for run in runs:
            try:
                pays = read_reviewer_pay(run.path)
            except CoverageError:
                continue  # not a grid run, or no task finished: reported elsewhere
            if pays:
                found.setdefault(label, []).append(pays)
    return found


def reviewer_pay_section(groups: dict[str, list[ReportedRun]]) -> list[Table | Figure]:
    """The table and the maps, where some grid run paid a reviewer; nothing otherwise."""
    from drago.report.heatmap import StageMaps, heatmap_png

    found = _pays(groups)
    if not found:
        return []
    rows = []
    panels: dict[str, dict[int, StageMaps]] = {}
    for label, runs in found.items():
        for stage in sorted({pay.stage for pays in runs for pay in pays}):
            at_stage = [pay for pays in runs for pay in pays if pay.stage == stage]
            first = at_stage[0]
            rows.append((label, f"{stage}: {first.task}", first.next_task, str(len(at_stage)),
                         format_summary([pay.threshold for pay in at_stage])[0],
                         format_summary([pay.old_rooms_paid for pay in at_stage])[0],
                         *(format_summary([pay.rooms[room]["reward"] for pay in at_stage])[0] for room in ROOMS)))
            panels.setdefault(label, {})[stage + 1] = StageMaps(first.next_task,
                                                                [pay.reward_cells for pay in at_stage])
    table = Table("reviewer-pay", "What the reviewer is paid",
                  "The intrinsic reward r = r_old − α·c of every grid transition when the next task begins (the "
                  "current model is then the old one), from each stage's checkpoint and its θ (paper §3.2). "
                  f"'old rooms paid': share of the transitions in the rooms of the tasks so far whose old-model "
                  f"term r_old exceeds {PAID}; then the mean r per room. Mean ± std [95% CI] over seeds.",
                  ("method", "old model: stage", "paid in task", "seeds", "θ", "old rooms paid",
                   *(f"mean r {room}" for room in ROOMS)), rows)
    png = heatmap_png(panels, label=PAY_LABEL, empty="no reviewer", stage_title="start of task")
    figure = Figure("reviewer-pay-maps", "Where the reviewer is paid",
                    "The intrinsic reward the reviewer plans for when each task begins (rows: methods; columns: "
                    "tasks from the second), the mean over each cell's 4 headings × 3 actions, averaged over "
                    "seeds, one colour scale for all panels. The task's start (○) and goal (★) are marked.",
                    png, REVIEWER_PAY_PNG)
    return [table, figure]


def _train_rows(run: ReportedRun) -> list[dict[str, str]]:
    try:
        with (run.path / LOG_FILES["train"]).open(newline="") as handle:
            return list(csv.DictReader(handle))
    except (OSError, UnicodeDecodeError, csv.Error):
        return []  # no train.csv yet, or an unreadable one: the runs table reports the run


def reviewer_reward_figure(groups: dict[str, list[ReportedRun]], colours: dict[str, str]) -> Figure | None:
    """What the reviewer earned during each task with a reviewer (columns), episode by episode: the old-model
    term, the cost, their difference and θ's running estimate (rows), mean over seeds with a 95% CI band."""
    series: dict[str, dict[str, dict[str, dict[int, list[float]]]]] = {}  # task -> column -> label -> x -> values
    tasks: list[str] = []
    for label, runs in groups.items():
        for run in runs:
            for row in _train_rows(run):
                if not row.get("reviewer_episode_reward"):
                    continue
                task, x = row["task"], as_number(row.get("env_step"))
                if task not in tasks:
                    tasks.append(task)
                for column, _ in REWARD_ROWS:
                    y = as_number(row.get(column))
                    if math.isfinite(x) and math.isfinite(y):
                        series.setdefault(task, {}).setdefault(column, {}).setdefault(label, {}).setdefault(
                            int(x), []).append(y)
    if not tasks:
        return None
    grid = [[Panel(task, "env steps in the task", ylabel, series[task].get(column, {})) for task in tasks]
            for column, ylabel in REWARD_ROWS]
    png = panels_png(grid, colours, rows_differ=True)
    if png is None:
        return None
    return Figure("reviewer-reward", "What the reviewer earned",
                  "Per task with a reviewer (columns), against the task's env steps: the sums over each reviewer "
                  "episode of the old-model term r_old, of the current model's cost c and of the reward r = "
                  "r_old − α·c the reviewer plans for, and the running estimate of θ the next task will use "
                  "(θ stays fixed during a task: the previous task's last estimate). Mean over seeds with the 95% "
                  "bootstrap CI as a band.", png, REVIEWER_REWARD_PNG)

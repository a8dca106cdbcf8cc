"""The report's "where the agents go" section (grid runs that recorded ``visitation.csv``): per method and stage,
the share of each agent's steps in each room, and maps of the reviewer's and learner's visits beside those of a
uniformly random agent given the same number of steps (docs: Evaluation, where the reviewer goes)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from drago.envs.fourrooms import SIZE
from drago.eval.coverage import ALL, GROUPS, room_group
from drago.report.content import Figure, Table
from drago.report.runs import ReportedRun
from drago.report.tables import format_summary
from drago.training.rundir import VISITATION_FILE
from drago.training.visitation import AGENTS, read_visitation

__all__ = ["VISITATION_PNG", "room_shares", "visitation_figure", "visitation_maps", "visitation_section",
           "visitation_table"]

VISITATION_PNG = "visitation.png"
ROOMS = tuple(group for group in GROUPS if group != ALL)  # room1..room4, corridor
# Shares below this are drawn as this: a cell visited once in 10,000 steps and one never visited look alike.
SHARE_FLOOR = 1e-4
SHARE_LABEL = "share of the agent's steps in the cell (log10)"


def visitation_maps(run_dir: str | Path) -> dict[tuple[int, str, str], np.ndarray]:
    """``{(stage, task, agent): (SIZE, SIZE) visits indexed [y, x]}`` from a run's ``visitation.csv``."""
    maps: dict[tuple[int, str, str], np.ndarray] = {}
    for row in read_visitation(Path(run_dir) / VISITATION_FILE):
        key = (int(row["stage"]), row["task"], row["agent"])
        grid = maps.setdefault(key, np.zeros((SIZE, SIZE), dtype=np.int64))
        grid[int(row["y"]), int(row["x"])] += int(row["visits"])
    return maps


def room_shares(visits: np.ndarray) -> dict[str, float]:
    """The share of a visit map's steps in each room and in the corridor cells between them."""
    total = float(visits.sum())
    shares = dict.fromkeys(ROOMS, 0.0)
    for y, x in zip(*np.nonzero(visits)):
        shares[room_group((int(x), int(y)))] += visits[y, x] / total
    return shares


def _by_method(groups: dict[str, list[ReportedRun]]) -> dict[str, list[dict[tuple[int, str, str], np.ndarray]]]:
    found = {label: [m for m in (visitation_maps(run.path) for run in runs) if m] for label, runs in groups.items()}
    return {label: maps for label, maps in found.items() if maps}


def visitation_table(groups: dict[str, list[ReportedRun]]) -> Table | None:
    """Share of each agent's steps per room, mean ± std [95% CI] over seeds, per method, stage and agent."""
    found = _by_method(groups)
    if not found:
        return None
    rows = []
    for label, runs in found.items():
        for stage, task, agent in sorted({key for maps in runs for key in maps}, key=lambda k: (k[0], AGENTS.index(k[2]))):
            seeds = [room_shares(maps[(stage, task, agent)]) for maps in runs if (stage, task, agent) in maps]
            steps = [int(maps[(stage, task, agent)].sum()) for maps in runs if (stage, task, agent) in maps]
            rows.append((label, f"{stage}: {task}", agent, str(len(seeds)), f"{round(np.mean(steps)):,}",
                         *(format_summary([s[room] for s in seeds])[0] for room in ROOMS)))
    return Table("visitation", "Where the agents go",
                 "Share of each agent's env steps in each room during each stage's task: the learner, DRAGO's "
                 "reviewer, and a uniformly random agent given the reviewer's steps (the learner's without a "
                 "reviewer) in the same task, the reference a reviewer that seeks old rooms must beat. Mean ± std "
                 "[95% CI] over seeds; corridor: the five cells joining the rooms.",
                 ("method", "stage: task", "agent", "seeds", "steps", *ROOMS), rows)


def visitation_figure(groups: dict[str, list[ReportedRun]]) -> bytes | None:
    """Rows: each method's reviewer (where it has one), then the uniformly random agent; columns: stages.

    Each panel is the share of the agent's steps in each cell, averaged over seeds, on one log colour scale."""
    from drago.report.heatmap import StageMaps, heatmap_png

    found = _by_method(groups)
    panels: dict[str, dict[int, StageMaps]] = {}
    random_panels: dict[int, StageMaps] = {}
    for label, runs in found.items():
        for maps in runs:
            for (stage, task, agent), visits in maps.items():
                share = np.log10(np.maximum(visits / max(visits.sum(), 1), SHARE_FLOOR))
                if agent == "reviewer":
                    panels.setdefault(f"{label}: reviewer", {}).setdefault(stage, StageMaps(task, [])).maps.append(share)
                elif agent == "random" and "reviewer" in {a for (s, _, a) in maps if s == stage}:
                    random_panels.setdefault(stage, StageMaps(task, [])).maps.append(share)
    if not panels:
        return None
    panels["uniformly random"] = random_panels
    return heatmap_png(panels, label=SHARE_LABEL, empty="no reviewer", stage_title="during task")


def visitation_section(groups: dict[str, list[ReportedRun]]) -> list[Table | Figure]:
    """The table and, where some run had a reviewer, its figure."""
    table = visitation_table(groups)
    if table is None:
        return []
    sections: list[Table | Figure] = [table]
    png = visitation_figure(groups)
    if png is not None:
        sections.append(Figure("visitation-maps", "Where the reviewer goes", "Share of the reviewer's env steps "
                               "in each cell during each stage's task (rows: methods; columns: stages), averaged "
                               "over seeds, on one log10 colour scale (shares under 1e-4 drawn as 1e-4), beside a "
                               "uniformly random agent given the same steps in the same task. The stage's start "
                               "(○) and goal (★) are marked.", png, VISITATION_PNG))
    return sections

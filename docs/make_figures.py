"""Draw every figure of the documentation from the result files in docs/data.

    .venv/bin/python docs/make_figures.py

Reads the small CSV files in docs/data (their sources are in docs/data/sources.json) and writes PNGs
into docs/figures. Nothing else: no run directories, no checkpoints. Rerunning it on unchanged data
gives byte-identical files, so a diff of docs/figures shows only real changes.
"""

from __future__ import annotations

import csv
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

DOCS = Path(__file__).resolve().parent
DATA = DOCS / "data"
FIGURES = DOCS / "figures"
ROOMS = ("room1", "room2", "room3", "room4")
DPI = 100
# No timestamp or version in the PNG, so unchanged data gives an unchanged file.
PNG_METADATA = {"Software": None}


def read(name: str) -> list[dict[str, str]]:
    with open(DATA / name, newline="") as f:
        return list(csv.DictReader(f))


def save(fig, name: str) -> None:
    FIGURES.mkdir(exist_ok=True)
    fig.savefig(FIGURES / name, dpi=DPI, metadata=PNG_METADATA)
    plt.close(fig)
    print(f"wrote {(FIGURES / name).relative_to(DOCS.parent)}")


def annotated_heatmap(ax, values, row_labels, col_labels, vmin, vmax, cmap="viridis", fmt="{:.2f}", norm=None):
    image = ax.imshow(values, cmap=cmap, vmin=None if norm else vmin, vmax=None if norm else vmax, norm=norm,
                      aspect="auto")
    ax.set_xticks(range(len(col_labels)), col_labels)
    ax.set_yticks(range(len(row_labels)), row_labels)
    ax.tick_params(length=0)
    for i in range(values.shape[0]):
        for j in range(values.shape[1]):
            value = values[i, j]
            if np.isnan(value):
                continue
            red, green, blue, _ = image.cmap(image.norm(value))
            light = 0.299 * red + 0.587 * green + 0.114 * blue > 0.5
            ax.text(j, i, fmt.format(value), ha="center", va="center", fontsize=10,
                    color="black" if light else "white")
    return image


def grid_retention_heatmap() -> None:
    """continual against drago: coverage of each room after each task (the README's figure)."""
    rows = read("grid_retention.csv")
    fig, axes = plt.subplots(1, 2, figsize=(9.0, 4.0), constrained_layout=True)
    for ax, method, title in zip(axes, ("continual", "drago"),
                                 ("continual: forgets each room when it moves on", "drago: keeps the old rooms")):
        matrix = np.full((4, 4), np.nan)
        for r in rows:
            if r["method"] == method:
                matrix[int(r["after_task"]) - 1, ROOMS.index(r["room"])] = float(r["mean"])
        image = annotated_heatmap(ax, matrix, [f"after task {i}" for i in range(1, 5)], ROOMS, 0.0, 1.0)
        ax.set_title(title)
    fig.colorbar(image, ax=axes, shrink=0.9, label="world-model accuracy (exact match)")
    fig.suptitle("minigrid-cpu: world-model coverage per room, mean of seeds 1-3")
    save(fig, "grid-retention-heatmap.png")


def grid_study_coverage() -> None:
    """Every study method: coverage per room after task 4, and ACC / BWT with 95% bootstrap CIs."""
    rows = read("grid_study_coverage.csv")
    methods = [r["method"] for r in rows]
    matrix = np.array([[float(r[room]) for room in ROOMS] for r in rows])
    fig, (left, right) = plt.subplots(1, 2, figsize=(10.0, 4.6), constrained_layout=True,
                                      gridspec_kw={"width_ratios": [1.1, 1.0]})
    annotated_heatmap(left, matrix, methods, ROOMS, 0.0, 1.0)
    left.set_title("coverage per room after the fourth task")
    y = np.arange(len(rows))
    for offset, metric, colour in ((-0.15, "acc", "tab:blue"), (0.15, "bwt", "tab:red")):
        mean = np.array([float(r[f"{metric}_mean"]) for r in rows])
        low = np.array([float(r[f"{metric}_ci_low"]) for r in rows])
        high = np.array([float(r[f"{metric}_ci_high"]) for r in rows])
        right.errorbar(mean, y + offset, xerr=(mean - low, high - mean), fmt="o", color=colour, capsize=3,
                       label=metric.upper())
    right.axvline(0.0, color="grey", lw=0.8)
    right.set_yticks(y, methods)
    right.invert_yaxis()
    right.set_xlim(-1.0, 1.0)
    right.set_xlabel("value, with 95% bootstrap CI")
    right.legend(loc="upper center", bbox_to_anchor=(0.5, -0.14), ncol=2)
    right.set_title("ACC (higher is better), BWT (< 0: forgetting)")
    fig.suptitle("Grid study, minigrid-cpu, seeds 1-3")
    save(fig, "grid-study-coverage.png")


def minigrid_cpu_learning() -> None:
    """continual's final % of optimal per room and seed, for the preset and the settings it replaced."""
    rows = read("minigrid_cpu_learning.csv")
    settings = list(dict.fromkeys(r["settings"] for r in rows))
    fig, ax = plt.subplots(figsize=(10.0, 4.4), constrained_layout=True)
    width = 0.8 / len(settings)
    markers = ("o", "s", "^", "D", "v")
    for k, setting in enumerate(settings):
        for room_index, room in enumerate(ROOMS):
            values = [float(r[room]) for r in rows if r["settings"] == setting and r[room]]
            x = np.full(len(values), room_index - 0.4 + (k + 0.5) * width)
            ax.scatter(x, values, marker=markers[k % len(markers)], color=f"C{k}", s=28,
                       label=setting if room_index == 0 else None, zorder=3)
    ax.axhline(80, color="grey", lw=0.8, ls="--")
    ax.set_xticks(range(4), ROOMS)
    ax.set_ylim(-5, 105)
    ax.set_ylabel("final return, % of DP optimum")
    ax.set_title("continual on minigrid-cpu: each point is one seed's last evaluation of a task")
    ax.legend(fontsize=9, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    ax.grid(axis="y", alpha=0.3)
    save(fig, "minigrid-cpu-learning.png")


def cheetah_cpu_learning() -> None:
    """cheetah-cpu: continual's learning curve on cheetah-run, and held-out retention of both methods."""
    curve = read("cheetah_cpu_run_curve.csv")
    retention = read("cheetah_cpu_retention.csv")
    fig, axes = plt.subplots(1, 2, figsize=(10.0, 4.2), constrained_layout=True,
                             gridspec_kw={"width_ratios": [1.0, 1.3]})
    ax = axes[0]
    ax.plot([int(r["env_steps"]) / 1000 for r in curve], [float(r["eval_return"]) for r in curve], "o-")
    ax.set_xlabel("env steps (thousands)")
    ax.set_ylabel("evaluation return")
    ax.set_title("continual on cheetah-run (seed 1)")
    ax.grid(alpha=0.3)

    tasks = ("cheetah-run", "cheetah-jump", "cheetah-run-backwards")
    ax = axes[1]
    matrix = np.full((6, 3), np.nan)
    labels = []
    for m_index, method in enumerate(("continual", "drago")):
        for stage in range(1, 4):
            labels.append(f"{method}, after {stage}")
        for r in retention:
            if r["method"] == method:
                matrix[m_index * 3 + int(r["after_stage"]) - 1, tasks.index(r["on_task"])] = float(r["mse"])
    norm = matplotlib.colors.LogNorm(vmin=0.1, vmax=40)
    annotated_heatmap(ax, matrix, labels, ("run", "jump", "run-backwards"), None, None, cmap="magma_r", norm=norm)
    ax.axhline(2.5, color="white", lw=2)
    ax.set_title("held-out one-step MSE (lower is better)")
    save(fig, "cheetah-cpu-learning.png")


def cheetah_cpu_fewshot() -> None:
    """cheetah-cpu few-shot test tasks, one seed, beside the paper's Table 1 (mean and std)."""
    fewshot = read("cheetah_cpu_fewshot.csv")
    paper = {r["task"]: r for r in read("paper_table1.csv")}
    paper_names = {"jump2run": "cheetah jump2run", "jump-and-run": "cheetah jump&run",
                   "jump2back": "cheetah jump2back", "jump-and-back": "cheetah jump&back"}
    cases = [r for r in fewshot if r["test_task"] in paper_names]
    fig, ax = plt.subplots(figsize=(9.0, 4.2), constrained_layout=True)
    x = np.arange(len(cases))
    bars = (("drago_20_episodes", "drago, 20 episodes", None), ("continual_20_episodes", "continual, 20 episodes", None),
            ("paper", "paper: DRAGO", "drago"), ("paper", "paper: Continual TD-MPC", "continual"))
    width = 0.2
    for k, (key, label, paper_method) in enumerate(bars):
        if paper_method is None:
            values, errors = [float(r[key]) for r in cases], None
        else:
            values = [float(paper[paper_names[r["test_task"]]][f"{paper_method}_mean"]) for r in cases]
            errors = [float(paper[paper_names[r["test_task"]]][f"{paper_method}_std"]) for r in cases]
        ax.bar(x + (k - 1.5) * width, values, width, yerr=errors, capsize=2, label=label, color=f"C{k}",
               alpha=1.0 if paper_method is None else 0.55, hatch=None if paper_method is None else "//")
    ax.set_xticks(x, [f"{r['test_task']} (after {r['after_stage']})" for r in cases])
    ax.set_ylabel("return")
    ax.set_ylim(0, 480)
    ax.set_title("cheetah-cpu few-shot test tasks (one seed) beside the paper's Table 1 (mean ± std)")
    ax.legend(ncol=2, loc="upper center")
    ax.grid(axis="y", alpha=0.3)
    save(fig, "cheetah-cpu-fewshot.png")


def method_cost() -> None:
    rows = read("method_cost.csv")
    methods = [r["method"] for r in rows]
    ratio = [float(r["ratio_to_continual"]) for r in rows]
    fig, ax = plt.subplots(figsize=(8.0, 4.0), constrained_layout=True)
    ax.barh(methods, ratio, color=["C0" if not m.startswith(("drago", "pseudo")) else "C1" for m in methods])
    ax.axvline(1.0, color="grey", lw=0.8)
    ax.invert_yaxis()
    ax.set_xlabel("CPU seconds per 10k-step task, relative to continual")
    ax.set_title("What each method costs on minigrid-cpu (one thread, task 2)")
    for i, value in enumerate(ratio):
        ax.text(value + 0.01, i, f"{value:.2f}", va="center", fontsize=9)
    ax.set_xlim(0, 1.55)
    save(fig, "method-cost.png")


def reviewer_pay() -> None:
    """DRAGO, seed 1: the reviewer's intrinsic reward on every cell when tasks 2-4 begin, and what it earned."""
    cells = read("reviewer_pay_cells_seed1.csv")
    terms = read("reviewer_terms_seed1.csv")
    tasks = list(dict.fromkeys(r["paid_in_task"] for r in cells))
    fig, axes = plt.subplots(1, len(tasks) + 1, figsize=(4.0 * (len(tasks) + 1), 3.8), constrained_layout=True,
                             gridspec_kw={"width_ratios": [1] * len(tasks) + [1.3]})
    maps = {task: np.full((27, 27), np.nan) for task in tasks}
    for r in cells:
        maps[r["paid_in_task"]][int(r["y"]), int(r["x"])] = float(r["mean_r"])
    low = min(np.nanmin(m) for m in maps.values())
    high = max(np.nanmax(m) for m in maps.values())
    cmap = matplotlib.colormaps["viridis"].with_extremes(bad="#b8b8b8")
    for ax, task in zip(axes, tasks):
        image = ax.imshow(maps[task], cmap=cmap, vmin=low, vmax=high, interpolation="nearest")
        ax.set_xticks([])
        ax.set_yticks([])
        ax.set_title(f"start of task {tasks.index(task) + 2}: {task}")
    fig.colorbar(image, ax=axes[: len(tasks)], shrink=0.85, label="reward r = r_old − α·c, mean over the cell")
    ax = axes[-1]
    names = list(dict.fromkeys(r["task"] for r in terms))
    x = np.arange(len(names))
    for offset, (column, label) in zip((-0.2, 0.2), (("old_term_per_episode", "Σ r_old"),
                                                      ("cost_per_episode", "Σ c"))):
        for half, alpha in (("first half", 0.5), ("second half", 1.0)):
            values = [float(r[column]) for name in names for r in terms if r["task"] == name
                      and r["reviewer_episodes"] == half]
            ax.bar(x + offset + (0.1 if half == "second half" else -0.1) / 2, values, width=0.18, alpha=alpha,
                   color="C0" if column.startswith("old") else "C1",
                   label=f"{label}, {half} of the task")
    ax.set_xticks(x, names)
    ax.set_ylabel("per reviewer episode (100 steps)")
    ax.set_title("what the reviewer earned")
    ax.legend(fontsize=8, frameon=False)
    fig.suptitle("minigrid-cpu, drago seed 1: where the reviewer is paid, and what it earned")
    save(fig, "reviewer-pay.png")


def main() -> None:
    plt.rcParams.update({"font.size": 11, "axes.titlesize": 11})
    grid_retention_heatmap()
    grid_study_coverage()
    minigrid_cpu_learning()
    cheetah_cpu_learning()
    cheetah_cpu_fewshot()
    method_cost()
    reviewer_pay()


if __name__ == "__main__":
    main()

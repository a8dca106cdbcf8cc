"""The paper's published few-shot numbers beside a report's own (paper §4.4, Table 1; its appendices).

The report puts every transfer case the paper has a number for beside the runs' score read the paper's way
(the return after the few-shot learner episodes), and says per case which method leads in the paper and
here, and whether the leader's 95% CI clears every other method's. Numbers are mean ± std over the paper's
seeds, as printed; the paper gives no CIs.
"""

from __future__ import annotations

from collections.abc import Sequence

from drago.envs.tasks import DMC_TRANSFER_TASKS
from drago.eval.stats import Summary, summarize
from drago.report.content import Table
from drago.report.runs import Case, ReportedRun, as_number, case_name
from drago.report.tables import DIGITS

__all__ = ["LEARNED_FRACTION", "PAPER_FEW_SHOT", "PAPER_TRAINING_RETURNS", "leader", "paper_tables",
           "paper_training_table"]

Cell = tuple[float, float]  # mean, std over the paper's seeds

#: Below this share of the task's DP optimum a method has not learned the case: on the grid's test tasks a
#: learner's own exploring episodes, before its planner has found the goal, average up to a few percent of
#: it, so a leader among returns this low says who wandered luckier, not whose model transfers (docs:
#: Reproducing the paper, the PETS study).
LEARNED_FRACTION = 0.05

_TABLE1: dict[str, dict[str, Cell]] = {  # paper Table 1, and the curiosity column of its appendix (cheetah)
    "jump2run": {"drago": (106.78, 32.01), "curiosity": (88.36, 25.81), "ewc": (54.72, 62.72),
                 "continual": (93.96, 39.29), "scratch": (26.54, 2.67)},
    "jump-and-run": {"drago": (248.92, 15.38), "curiosity": (165.35, 67.01), "ewc": (156.98, 99.68),
                     "continual": (128.58, 100.14), "scratch": (182.77, 28.58)},
    "jump2back": {"drago": (331.85, 11.05), "curiosity": (133.81, 23.07), "ewc": (29.93, 7.15),
                  "continual": (73.98, 38.45), "scratch": (45.15, 4.92)},
    "jump-and-back": {"drago": (147.30, 34.29), "curiosity": (138.77, 45.55), "ewc": (117.92, 1.20),
                      "continual": (140.82, 28.00), "scratch": (129.75, 20.44)},
    "walk2run": {"drago": (332.38, 20.07), "ewc": (287.02, 37.80), "continual": (229.14, 33.71),
                 "scratch": (52.11, 3.41)},
    "run2back": {"drago": (145.98, 17.96), "ewc": (150.19, 2.77), "continual": (128.56, 9.47),
                 "scratch": (60.49, 9.40)},
    "back2run": {"drago": (229.79, 9.77), "ewc": (254.09, 70.29), "continual": (241.39, 42.64),
                 "scratch": (40.76, 18.34)},
    "stand2run": {"drago": (265.50, 8.40), "ewc": (177.02, 62.48), "continual": (182.71, 30.74),
                  "scratch": (64.02, 31.54)},
}

#: ``(agent kind, case as the report names it, stage K) -> {method: (mean, std)}``: the paper's few-shot returns.
PAPER_FEW_SHOT: dict[tuple[str, str, int], dict[str, Cell]] = {
    **{("tdmpc", name, DMC_TRANSFER_TASKS[name].stage): cells for name, cells in _TABLE1.items()},
    # Appendix: relearning walker's training tasks from the final world model (the fourth stage), "reward at
    # 40k steps": 40 learner episodes of 1,000 env steps (`drago transfer RUN --task walker-run --after 4
    # --episodes 40 --few-shot-episodes 40`).
    ("tdmpc", "walker-run", 4): {"drago": (371.46, 12.79), "continual": (300.52, 27.07)},
    ("tdmpc", "walker-walk", 4): {"drago": (740.89, 54.90), "continual": (685.66, 43.05)},
    ("tdmpc", "walker-stand", 4): {"drago": (871.17, 55.07), "continual": (463.60, 107.12)},
    # Appendix E: DRAGO-PETS against continual PETS on the grid, dense reward (the test tasks' own is sparse).
    ("pets", "room1to3 (dense)", 3): {"drago": (233.21, 21.07), "continual": (150.84, 62.37)},
    ("pets", "room1to2 (dense)", 2): {"drago": (101.03, 116.21), "continual": (161.70, 44.31)},
    ("pets", "room1to3 (dense)", 4): {"drago": (138.26, 99.05), "continual": (43.04, 111.93)},
    ("pets", "room3to4 (dense)", 4): {"drago": (234.65, 41.71), "continual": (147.80, 105.84)},
}

#: The appendix's final return of each training task ("1M steps", one value per cell), for its TD-MPC agent:
#: ``(agent kind, method) -> {task: return}``.
PAPER_TRAINING_RETURNS: dict[tuple[str, str], dict[str, float]] = {
    ("tdmpc", "drago"): {"cheetah-run": 652.53, "cheetah-jump": 587.24, "cheetah-run-backwards": 624.09,
                         "walker-run": 708.74, "walker-walk": 954.56, "walker-walk-backwards": 953.8,
                         "walker-stand": 972.46},
    ("tdmpc", "continual"): {"cheetah-run": 675.31, "cheetah-jump": 646.30, "cheetah-run-backwards": 580.59,
                             "walker-run": 693.61, "walker-walk": 959.31, "walker-walk-backwards": 956.42,
                             "walker-stand": 982.69},
}


def _paper_key(runs: Sequence[ReportedRun], case: Case) -> tuple[str, str, int]:
    return (runs[0].cfg.agent.kind, case[0], case[1])


def leader(summaries: dict[str, Summary]) -> tuple[str, bool | None]:
    """The method with the highest mean, and whether its 95% CI lies above every other method's (None when
    a CI rests on one seed and cannot say)."""
    kept = {method: s for method, s in summaries.items() if s.n > 0}
    best = max(kept, key=lambda method: kept[method].mean)
    if any(s.n < 2 for s in kept.values()):
        return best, None
    return best, all(kept[best].ci_low > s.ci_high for method, s in kept.items() if method != best)


def _paper_leader(cells: dict[str, Cell], methods: Sequence[str]) -> str:
    return max(methods, key=lambda method: cells[method][0])


def paper_tables(tgroups: dict[str, list[ReportedRun]], cases: list[Case],
                 few_shot: dict[str, dict[str, float]]) -> list[Table]:
    """The paper's few-shot numbers beside the transfers' (one row per case and method), and per case the
    leader in the paper and here, over the methods both have; nothing when no case has a paper number.

    ``few_shot`` maps a transfer directory (as a string) to its score ``{"return": ..., "fraction_of_optimal":
    ...}`` at equal learner episodes, the paper's reading (the fraction where the task has a known optimum).
    """
    rows, verdicts = [], []
    for case in cases:
        here: dict[str, Summary] = {}
        fractions: dict[str, Summary] = {}
        cells: dict[str, Cell] = {}
        for label, runs in tgroups.items():
            mine = [run for run in runs if run.case == case]
            paper = PAPER_FEW_SHOT.get(_paper_key(mine, case)) if mine else None
            method = mine[0].method if mine else None
            if paper is None or method not in paper:
                continue
            scores = [few_shot.get(str(run.path), {}) for run in mine]
            here[label] = summarize([as_number(score.get("return")) for score in scores])
            fractions[label] = summarize([as_number(score.get("fraction_of_optimal")) for score in scores])
            cells[label] = paper[method]
            mean, std = paper[method]
            rows.append((case_name(case), label, f"{mean:.2f} ± {std:.2f}", here[label].format(DIGITS), str(here[label].n)))
        compared = [label for label in here if here[label].n > 0]
        if len(compared) >= 2:
            if all(fractions[label].n == here[label].n and fractions[label].mean < LEARNED_FRACTION
                   for label in compared):
                best, separates = f"none: every mean under {LEARNED_FRACTION:.0%} of the optimum", "–"
            else:
                best, flag = leader({label: here[label] for label in compared})
                separates = {True: "yes", False: "no", None: "one seed"}[flag]
            verdicts.append((case_name(case), ", ".join(compared), _paper_leader(cells, compared), best,
                             separates))
    if not rows:
        return []
    tables = [Table("paper-few-shot", "Transfer beside the paper",
                    "The paper's few-shot return (paper §4.4, Table 1 and its appendix with curiosity; the "
                    "appendix's walker relearning after 40k steps; Appendix E for PETS: mean ± std over its seeds) "
                    "beside this report's at equal learner episodes, the "
                    "paper's reading: mean ± std [95% bootstrap CI of the mean] over seeds. The paper's budgets "
                    "are those of its presets; a CPU preset's are much smaller, so compare the ranking, not the "
                    "returns.",
                    ("case", "method", "paper", "here", "seeds"), rows)]
    if verdicts:
        tables.append(Table("paper-leaders", "Who leads, in the paper and here",
                            "Per case, over the methods both the paper and this report have: the method with the "
                            "highest mean return in the paper and here, and whether the leader's 95% CI here lies "
                            "above every other method's CI (\"one seed\": some method has a single seed, no CI). "
                            f"No leader where every method's mean is under {LEARNED_FRACTION:.0%} of the task's DP "
                            "optimum: none has learned the case.",
                            ("case", "methods", "paper's leader", "leader here", "CI separates"), verdicts))
    return tables


def paper_training_table(groups: dict[str, list[ReportedRun]], tasks: list[str]) -> list[Table]:
    """The appendix's final training returns beside the runs' (TD-MPC runs of the methods it reports)."""
    rows = []
    for label, runs in groups.items():
        paper = PAPER_TRAINING_RETURNS.get((runs[0].cfg.agent.kind, runs[0].method)) if runs else None
        if paper is None:
            continue
        for task in tasks:
            if task not in paper:
                continue
            s = summarize([as_number(run.finished[task].get("final_eval_return")) for run in runs if task in run.finished])
            rows.append((label, task, f"{paper[task]:.2f}", s.format(DIGITS), str(s.n)))
    if not rows:
        return []
    return [Table("paper-training", "Training returns beside the paper",
                  "The appendix's final return of each training task (one value per cell, after the paper's 1M "
                  "steps a task) beside this report's final evaluation return: mean ± std [95% CI] over seeds.",
                  ("method", "task", "paper", "here", "seeds"), rows)]

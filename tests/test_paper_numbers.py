"""The paper's published numbers beside a report's: the right cells, the leader and whether its CI separates."""

from __future__ import annotations

import csv
from pathlib import Path

import pytest

from drago.api import load_config
from drago.envs.tasks import DMC_TRANSFER_TASKS
from drago.eval.stats import Summary
from drago.report.paper import PAPER_FEW_SHOT, PAPER_TRAINING_RETURNS, leader, paper_tables
from drago.report.runs import ReportedRun, label_runs

DOCS_DATA = Path(__file__).resolve().parents[1] / "docs" / "data"


def transfer(tmp_path: Path, preset: str, method: str, seed: int, task: str, after: int) -> ReportedRun:
    cfg = load_config(preset, [f"env.tasks=[{task}]", f"transfer.checkpoint={tmp_path}/task{after}.pt",
                               f"transfer.after={after}"], method=method, seed=seed)
    if cfg.transfer.reward is not None:  # as `drago transfer` writes it into the transfer's config
        cfg.env.dense_reward = cfg.transfer.reward == "dense"
    return ReportedRun(path=tmp_path / f"{method}-{seed}-{task}-{after}", cfg=cfg, summary=None, eval_rows=[])


def summary(mean: float, low: float, high: float, n: int = 3) -> Summary:
    return Summary(n=n, mean=mean, std=1.0, iqm=mean, ci_low=low, ci_high=high)


def test_the_leader_separates_only_when_its_ci_clears_every_other():
    assert leader({"drago": summary(10, 9, 11), "continual": summary(5, 4, 6)}) == ("drago", True)
    assert leader({"drago": summary(10, 7, 13), "continual": summary(8, 6, 9)}) == ("drago", False)
    assert leader({"drago": summary(10, 9, 11), "ewc": summary(12, 12, 12, n=1)}) == ("ewc", None)


def test_pets_transfers_beside_the_appendix(tmp_path):
    returns = {"drago": [230.0, 240.0, 250.0], "continual": [100.0, 150.0, 200.0]}
    runs = [transfer(tmp_path, "minigrid-pets-cpu", method, seed, "room1to3", 3)
            for method in returns for seed in (1, 2, 3)]
    few_shot = {str(run.path): {"return": returns[run.method][run.seed - 1]} for run in runs}
    cases = sorted({run.case for run in runs})
    assert cases == [("room1to3 (dense)", 3)]  # the appendix's reward, not the test task's own (sparse)
    tables = paper_tables(label_runs(runs), cases, few_shot)
    beside, leaders = (table.rows for table in tables)
    drago = next(row for row in beside if row[1] == "drago")
    assert drago[:3] == ("room1to3 (dense) after 3", "drago", "233.21 ± 21.07") and drago[4] == "3"
    assert drago[3].startswith("240.00 ± 10.00 [")
    assert leaders == [("room1to3 (dense) after 3", "drago, continual", "drago", "drago", "yes")]


def test_no_leader_is_named_where_no_method_learned_the_case(tmp_path):
    # What the CPU PETS study measured after 20 episodes: returns of a few tenths out of a dense optimum of 266.5,
    # whose CIs can still "separate".
    returns = {"drago": [0.0, 0.0, 0.0], "continual": [0.5, 0.8, 0.1]}
    runs = [transfer(tmp_path, "minigrid-pets-cpu", method, seed, "room3to4", 4)
            for method in returns for seed in (1, 2, 3)]

    def verdict(scale: float) -> tuple:
        few_shot = {str(run.path): {"return": scale * returns[run.method][run.seed - 1],
                                    "fraction_of_optimal": scale * returns[run.method][run.seed - 1] / 266.5}
                    for run in runs}
        return paper_tables(label_runs(runs), [("room3to4 (dense)", 4)], few_shot)[1].rows[0][3:]

    assert verdict(1.0) == ("none: every mean under 5% of the optimum", "–")
    # 25 times those returns (continual at 4.4% of the optimum on average, one seed at 7.5%) is still none;
    # 40 times (7.0%) names continual, whose CI lies above drago's zeros.
    assert verdict(25.0)[0].startswith("none")
    assert verdict(40.0) == ("continual", "yes")


def test_cases_without_a_paper_number_get_no_table(tmp_path):
    # The paper reports grid transfers of TD-MPC as curves only, and dense PETS transfers of two methods only.
    runs = [transfer(tmp_path, "smoke", "drago", 1, "room1to2", 2),
            transfer(tmp_path, "minigrid-pets-cpu", "scratch", 1, "room1to3", 3)]
    assert paper_tables(label_runs(runs), sorted({run.case for run in runs}), {}) == []


def test_a_transfer_with_the_other_reward_is_a_case_of_its_own(tmp_path):
    sparse = transfer(tmp_path, "smoke", "drago", 1, "room1to2", 2)
    dense = transfer(tmp_path, "smoke", "drago", 1, "room1to2", 2)
    dense.cfg.env.dense_reward = True
    relearn = transfer(tmp_path, "smoke", "drago", 1, "room1", 2)  # a training room: dense is its own reward
    assert (sparse.case, dense.case, relearn.case) == (("room1to2", 2), ("room1to2 (dense)", 2), ("room1", 2))


def test_a_method_with_two_agents_is_reported_as_two(tmp_path):
    runs = [transfer(tmp_path, "minigrid-pets-cpu", "drago", 1, "room1to3", 3),
            transfer(tmp_path, "minigrid-pets-cpu", "drago", 2, "room1to3", 3)]
    runs[1].cfg.agent.kind = "tdmpc"
    assert set(label_runs(runs)) == {"drago [pets]", "drago [tdmpc]"}


def test_runs_of_a_method_with_other_settings_are_reported_apart(tmp_path):
    def run(seed: int, *overrides: str) -> ReportedRun:
        cfg = load_config("minigrid-cpu", list(overrides), method="drago-no-rehearsal", seed=seed)
        return ReportedRun(path=tmp_path / f"{seed}-{len(overrides)}", cfg=cfg, summary=None, eval_rows=[])

    runs = [run(1), run(2, "agent.tdmpc.precision=float32"), run(1, "method.reviewer.threshold_offset=3"),
            run(2, "method.reviewer.threshold_offset=3"), run(3, "train.reviewer_steps_per_task=null")]
    groups = label_runs(runs)
    # Seeds, and what a run resolves for its machine, do not split a group; a method's setting and a budget do.
    assert {label: len(members) for label, members in groups.items()} == {
        "drago-no-rehearsal [train.reviewer_steps_per_task=5000, method.reviewer.threshold_offset=0.0]": 2,
        "drago-no-rehearsal [train.reviewer_steps_per_task=5000, method.reviewer.threshold_offset=3.0]": 2,
        "drago-no-rehearsal [train.reviewer_steps_per_task=null, method.reviewer.threshold_offset=0.0]": 1}
    # A setting the method does not act on splits nothing: without a reviewer both schedule clocks count alike.
    clocks = [ReportedRun(path=tmp_path / f"clock-{clock}", summary=None, eval_rows=[],
                          cfg=load_config("minigrid-cpu", [f"agent.schedule_clock={clock}"], method=method, seed=1))
              for method in ("continual", "drago") for clock in ("task", "learner")]
    assert {label: len(members) for label, members in label_runs(clocks).items()} == {
        "continual": 2, "drago [agent.schedule_clock=task]": 1, "drago [agent.schedule_clock=learner]": 1}
    # Transfers of one method and setting stay one group across cases and budgets (each case is its own).
    cases = [transfer(tmp_path, "smoke", "drago", 1, "room1to2", 2), transfer(tmp_path, "smoke", "drago", 1, "room1to3", 3)]
    cases[1].cfg.train.learner_steps_per_task = 4000
    assert list(label_runs(cases)) == ["drago"]


def test_a_transfer_is_named_after_the_run_it_came_from(tmp_path):
    """A report that splits a method by a setting names that method's transfers the same way in its transfer
    tables, with a setting that sets the transfers themselves apart after it."""
    from drago.report.build import _label_transfers

    def source(seed: int, offset: int) -> ReportedRun:
        cfg = load_config("minigrid-cpu", [f"method.reviewer.threshold_offset={offset}"], method="drago-no-rehearsal",
                          seed=seed)
        return ReportedRun(path=tmp_path / f"run-{seed}-{offset}", cfg=cfg, summary=None, eval_rows=[])

    runs = [source(1, 0), source(1, 3)]
    label_runs(runs)
    usual = transfer(tmp_path, "minigrid-cpu", "drago-no-rehearsal", 1, "room1to2", 2)
    cheaper = transfer(tmp_path, "minigrid-cpu", "drago-no-rehearsal", 1, "room1to3", 3)
    cheaper.cfg.method.reviewer.cost_coef = 0.25
    alone = transfer(tmp_path, "minigrid-cpu", "drago", 1, "room1to2", 2)  # a transfer given without its run
    groups = _label_transfers([usual, cheaper, alone], {usual.path: runs[0], cheaper.path: runs[0]})
    base = "drago-no-rehearsal [method.reviewer.threshold_offset=0.0]"
    assert list(groups) == [f"{base} [method.reviewer.cost_coef=0.5]", f"{base} [method.reviewer.cost_coef=0.25]",
                            "drago"]
    assert list(_label_transfers([usual], {usual.path: runs[0]})) == [base]


def test_the_docs_tables_hold_the_same_numbers():
    with (DOCS_DATA / "paper_table1.csv").open(newline="") as handle:
        for row in csv.DictReader(handle):
            name = next(t.name for t in DMC_TRANSFER_TASKS.values() if t.paper_name.lower() == row["task"])
            cells = PAPER_FEW_SHOT[("tdmpc", name, DMC_TRANSFER_TASKS[name].stage)]
            for method in ("drago", "ewc", "continual", "scratch"):
                assert cells[method] == pytest.approx((float(row[f"{method}_mean"]), float(row[f"{method}_std"])))
    with (DOCS_DATA / "paper_training_returns.csv").open(newline="") as handle:
        rows = {row["method"]: row for row in csv.DictReader(handle)}
    for method, label in (("drago", "DRAGO"), ("continual", "Continual TDMPC")):
        paper = PAPER_TRAINING_RETURNS[("tdmpc", method)]
        assert {task: float(rows[label][task]) for task in paper} == paper


def test_relearning_walker_from_the_final_model_meets_the_appendix(tmp_path):
    runs = [transfer(tmp_path, "walker-cpu", method, seed, "walker-stand", 4)
            for method in ("drago", "continual") for seed in (1, 2)]
    few_shot = {str(run.path): {"return": 800.0 if run.method == "drago" else 500.0} for run in runs}
    beside, leaders = (table.rows for table in paper_tables(label_runs(runs), [("walker-stand", 4)], few_shot))
    assert [row[:3] for row in beside] == [("walker-stand after 4", "drago", "871.17 ± 55.07"),
                                           ("walker-stand after 4", "continual", "463.60 ± 107.12")]
    assert leaders == [("walker-stand after 4", "drago, continual", "drago", "drago", "yes")]

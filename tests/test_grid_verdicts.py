"""The results page's verdicts on the paper's claims (docs/make_grid_results.py), on hand-made units: a claim is
confirmed only where the 95% CIs over seeds separate, contradicted where they separate the other way, and
pending until each side has two seeds."""

from __future__ import annotations

import importlib.util
from pathlib import Path

_PATH = Path(__file__).resolve().parents[1] / "docs" / "make_grid_results.py"
_SPEC = importlib.util.spec_from_file_location("make_grid_results", _PATH)
grid = importlib.util.module_from_spec(_SPEC)
_SPEC.loader.exec_module(grid)

CASES = ("room1to2-after2", "room1to3-after3", "room1to3-after4", "room3to4-after4")


def unit(method: str, seed: int, old_rooms: float, final: float = 0.97, offset: float = 0.0,
         zero_shot: float = 0.0, transfer: float | None = None) -> dict:
    """A unit whose rooms 1-3 are covered at ``old_rooms`` after task 4, every room ended at ``final`` of its
    optimum, and (with ``transfer``) four dense transfer cases scoring ``transfer`` on every reading."""
    readings = {} if transfer is None else {
        case: {"reward": "dense", **{reading: transfer for reading in grid.TRANSFER_READINGS}} for case in CASES}
    return {"method": method, "seed": seed, "threshold_offset": offset,
            "final": {room: final for room in grid.ROOMS},
            "coverage": {(4, room): old_rooms for room in grid.ROOMS[:3]},
            "zero_shot": {(4, task): zero_shot for task in grid.TEST_TASKS},
            "transfers": readings}


def row(rows: list[tuple[str, str, str]], starts: str) -> tuple[str, str, str]:
    return next(r for r in rows if r[0].startswith(starts))


def test_retention_is_confirmed_only_when_the_cis_separate():
    continual = [unit("continual", s, v) for s, v in zip((1, 2, 3), (0.10, 0.12, 0.14))]
    separate = [unit("drago", s, v) for s, v in zip((1, 2, 3), (0.86, 0.88, 0.90))]
    overlapping = [unit("drago-no-rehearsal", s, v) for s, v in zip((1, 2, 3), (0.05, 0.30, 0.13))]
    below = [unit("drago-no-reviewer", s, v) for s, v in zip((1, 2, 3), (0.01, 0.02, 0.03))]
    rows = grid.verdicts(continual + separate + overlapping + below)
    assert row(rows, "DRAGO keeps rooms 1-3")[1] == "confirmed (CIs separate)"
    assert row(rows, "the reviewer alone retains")[1] == "not separated by the CIs"
    assert row(rows, "rehearsal alone retains")[1] == "contradicted (CIs separate the other way)"
    assert "drago 0.88 ± 0.02" in row(rows, "DRAGO keeps rooms 1-3")[2]


def test_one_seed_is_pending_and_a_failed_room_is_named():
    rows = grid.verdicts([unit("continual", 1, 0.1), unit("drago", 1, 0.9), unit("drago", 2, 0.9, final=0.5)])
    assert row(rows, "DRAGO keeps rooms 1-3")[1] == "pending: 2 and 1 of 3 seeds recorded"
    learns = row(rows, "`drago` learns every room")[1]
    assert learns.startswith("fails: seed 2 room1 0.50") and learns.endswith("(2 of 3 seeds)")
    assert row(rows, "`drago-no-reviewer` learns every room")[1] == "pending: no seed recorded"


def test_a_failed_room_says_whether_its_learner_had_settled():
    # room1's optimum is 200: of its last 20 training episodes 15 reach 100 (half), 5 do not; the 5 episodes
    # before them, all at 0, are too early to count. room2 has no optimum and so no reading.
    train = ([{"task": "room1", "episode_reward": "0"}] * 5 + [{"task": "room1", "episode_reward": "100"}] * 15
             + [{"task": "room1", "episode_reward": "99.9"}] * 5 + [{"task": "room2", "episode_reward": "5"}])
    late = grid._late_success(train, {"room1": 200.0})
    assert late == {"room1": 0.75}
    failed = unit("drago", 1, 0.9, final=0.5)
    failed["late_success"] = late
    learns = row(grid.verdicts([failed]), "`drago` learns every room")[1]
    assert learns.startswith("fails: seed 1 room1 0.50 (last 20 training episodes: 75% reached half the optimum)")


def test_the_reviewer_study_and_the_dense_transfers_are_judged_against_continual():
    main = [unit("continual", s, 0.1 + 0.01 * s) for s in (1, 2, 3)]
    reviewer = [unit("drago-no-rehearsal", s, 0.5 + 0.01 * s, offset=3.0) for s in (1, 2, 3)]
    dense = ([unit("drago", s, 0.9, transfer=0.6 + 0.01 * s) for s in (1, 2)]
             + [unit("continual", s, 0.1, transfer=0.6 + 0.02 * s) for s in (1, 2, 3)])
    rows = grid.verdicts(main, reviewer, dense)
    paid = row(rows, "the reviewer alone, paid against θ − 3,")
    assert paid[1] == "confirmed (CIs separate)" and paid[2].startswith("drago-no-rehearsal (θ − 3) 0.52")
    for reading in ("few-shot at equal learner episodes", "few-shot at equal env steps", "mean over the learning",
                    "end of the learning curve"):
        claim, verdict, _ = next(r for r in rows if reading in r[0])
        assert "dense reward" in claim and verdict == "not separated by the CIs so far (2 and 3 of 3 seeds)"


def test_the_reviewer_at_twice_the_budget_is_judged_against_continual_at_twice_the_budget():
    main = [unit("continual", s, 0.5 + 0.01 * s) for s in (1, 2, 3)]  # against these the 2× reviewer would lose
    doubled = [{**unit(method, s, level + 0.01 * s, offset=offset), "steps_per_task": 20000} for s in (1, 2, 3)
               for method, level, offset in (("drago-no-rehearsal", 0.30, 3.0), ("continual", 0.10, 0.0))]
    claim, verdict, numbers = row(grid.verdicts(main, reviewer_2x_units=doubled),
                                  "the reviewer alone, paid against θ − 3, retains more than `continual` at twice")
    assert "20,000 steps a task" in claim and verdict == "confirmed (CIs separate)"
    assert numbers.startswith("drago-no-rehearsal (θ − 3, 2×) 0.32") and "continual (2×) 0.12" in numbers
    assert not any("twice" in r[0] for r in grid.verdicts(main))  # no such study recorded: no such row


def test_a_unit_without_all_four_dense_cases_is_left_out_of_the_transfer_claims():
    partial = unit("drago", 1, 0.9, transfer=0.7)
    del partial["transfers"][CASES[0]]
    rows = grid.verdicts([], [], [partial, unit("drago", 2, 0.9, transfer=0.7), unit("continual", 1, 0.1, transfer=0.1),
                                  unit("continual", 2, 0.1, transfer=0.1)])
    assert row(rows, "a retained DRAGO model learns")[1] == "pending: 1 and 2 of 3 seeds recorded"


def test_a_learning_curve_is_read_by_its_mean_its_last_tenth_and_when_it_reached_half():
    # 100 learner episodes evaluated after each, and before the first: the goal found late, the optimum reached
    # for the last 10 evaluations; a curve too short for a tenth ends at its last evaluation
    late = [(episode, 0.0) for episode in range(91)] + [(episode, 1.0) for episode in range(91, 101)]
    assert grid.curve_readings(late) == {"curve_mean": 10 / 101, "curve_end": 1.0, "episodes_to_half": 91}
    never = grid.curve_readings([(0, 0.0), (5, 0.49), (10, 0.3)])
    assert never["curve_end"] == 0.3 and never["episodes_to_half"] is None
    assert grid.curve_readings([(0, 0.0), (5, 0.5)])["episodes_to_half"] == 5  # evaluated every 5 episodes
    assert grid.curve_readings([]) == {"curve_mean": None, "curve_end": None, "episodes_to_half": None}


def test_the_dense_table_counts_the_cases_each_method_ended_learned():
    learned = unit("drago", 1, 0.9, transfer=0.3)
    for case, end in zip(CASES, (0.95, 0.80, 0.79, 0.05)):  # the bar is inclusive: two of four cases
        learned["transfers"][case]["curve_end"] = end
    units = [learned, unit("drago", 2, 0.9, transfer=0.9), unit("scratch", 1, 0.0, transfer=0.1)]
    table = grid.dense_table(units)
    drago = next(line for line in table if line.startswith("| `drago`"))
    assert drago.endswith("| 6 of 8 (2 / 4) |") and "| 1, 2 |" in drago
    assert drago.split("|")[-3].startswith(" 0.77 ± 0.18")  # the end: seed 1 ends at 0.65 (its four cases), seed 2 0.90
    assert next(line for line in table if line.startswith("| `scratch`")).endswith("| 0 of 4 (0) |")
    assert grid.dense_table([]) == []
    cases = grid.dense_cases_table(units)
    # seeds 1-3 go unnamed; fewer are named
    assert cases[2] == f"| {CASES[0]} | seeds 1, 2: 0.95 / 0.90, 2 of 2 learned | seed 1: 0.10, 0 of 1 learned |"
    assert cases[4].startswith(f"| {CASES[2]} | seeds 1, 2: 0.79 / 0.90, 1 of 2 learned |")
    full = grid.dense_cases_table([unit("continual", s, 0.1, transfer=0.85) for s in (1, 2, 3)])
    assert full[2] == f"| {CASES[0]} | 0.85 / 0.85 / 0.85, 3 of 3 learned |"

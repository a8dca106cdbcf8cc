"""`drago report`: world-model heatmaps and the one-page HTML / Markdown report of a set of runs.

Three tiny smoke runs (seconds each) stand for a real comparison with gaps: continual seed 1 finished
its two tasks, continual seed 2 stopped after the first of two (a copy of a finished run cut back to
the state it had then), and drago has one seed of a one-task sequence. Transfers (room1to2 after 2, two
learner episodes) of a continual and a two-task drago run, and copies of them standing for more seeds,
test the transfer section; a one-task cheetah run tests learning curves without a known optimum.
"""

from __future__ import annotations

import base64
import csv
import io
import json
import os
import re
import shutil
import subprocess
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pytest
import yaml
from PIL import Image

from drago import cli
from drago.envs.fourrooms import SIZE, is_traversable, traversable_cells
from drago.eval.zero_shot import ZERO_SHOT_FILE, write_zero_shot_csv, zero_shot_matrix
from drago.eval.coverage import COVERAGE_FILE, cell_scores, coverage_of_run, grid_transitions, write_coverage_csv
from drago.report.heatmap import StageMaps, heatmap_png, run_cell_scores
from drago.report import ReportError, build_report, find_run_dirs
from drago.training.run import resume

SMOKE = ["--no-progress", "train.tensorboard=false", "train.steps_per_task=200", "train.eval_freq=100"]
TABLES = ("runs", "returns", "coverage", "metrics", "zero-shot", "zero-shot-metrics", "visitation")
TRANSFER_TABLES = ("transfer-episodes", "transfer-env-steps", "transfer-training")
CASE = "room1to2-after2"


def train(out: Path, method: str, seed: int, tasks: str) -> Path:
    assert cli.main(["train", "smoke", "--out", str(out), "--method", method, "--seed", str(seed),
                     f"env.tasks={tasks}", *SMOKE]) == 0
    return out


def cut_back_to_first_task(finished: Path, out: Path) -> Path:
    """The run directory as it was when the first task had finished and the second had not."""
    shutil.copytree(finished, out, ignore=shutil.ignore_patterns("task2_*", "summary.json"))
    with (out / "eval.csv").open(newline="") as handle:
        reader = csv.DictReader(handle)
        columns, rows = reader.fieldnames, [r for r in reader if r["task_index"] == "0"]
    with (out / "eval.csv").open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=columns)
        writer.writeheader()
        writer.writerows(rows)
    resume(out, progress=False).write_summary()
    return out


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("runs")
    staging = tmp_path_factory.mktemp("staging")
    return {
        "c1": train(root / "continual-seed1", "continual", 1, "[room1,room2]"),
        "c2": cut_back_to_first_task(train(staging / "continual-seed2", "continual", 2, "[room1,room2]"),
                                     root / "continual-seed2"),
        "d1": train(root / "drago-seed1", "drago", 1, "[room1]"),
    }


def add_transfer(run: Path) -> Path:
    """room1to2 learned from the run's stage-2 world model in two learner episodes."""
    assert cli.main(["transfer", str(run), "--no-progress", "--task", "room1to2", "--after", "2",
                     "--episodes", "2"]) == 0
    return run / "transfer" / CASE


def copy_as_seed(run: Path, out: Path, seed: int, ignore: tuple[str, ...] = ()) -> Path:
    """A copy of a run (or transfer) directory under another seed, standing for a run of that seed."""
    shutil.copytree(run, out, ignore=shutil.ignore_patterns(*ignore))
    for config in [out / "config.yaml", *out.glob("transfer/*/config.yaml")]:
        data = yaml.safe_load(config.read_text())
        data["train"]["seed"] = seed
        config.write_text(yaml.safe_dump(data, sort_keys=False))
    return out


def unfinish(transfer: Path, episodes: int) -> Path:
    """The transfer as it was after ``episodes`` learner episodes: no summary, later episodes and
    evaluations cut."""
    (transfer / "summary.json").unlink()
    for name in ("eval.csv", "train.csv"):
        with (transfer / name).open(newline="") as handle:
            reader = csv.DictReader(handle)
            columns, rows = reader.fieldnames, [r for r in reader if int(r["episode"]) <= episodes]
        with (transfer / name).open("w", newline="") as handle:
            writer = csv.DictWriter(handle, fieldnames=columns)
            writer.writeheader()
            writer.writerows(rows)
    return transfer


@pytest.fixture(scope="module")
def transfers(runs, tmp_path_factory) -> dict[str, Path]:
    """Sequence runs continual seeds 1-2 and drago seed 1 in one folder, transfers of continual seed 1
    and drago seed 1 inside them; drago seeds 2 (finished) and 3 (one of two episodes) as transfer
    directories alone, elsewhere; continual seed 2 has no transfer."""
    root = tmp_path_factory.mktemp("with-transfers")
    alone = tmp_path_factory.mktemp("transfers-alone")
    c1 = root / "continual-seed1"
    shutil.copytree(runs["c1"], c1)
    d1 = train(root / "drago-seed1", "drago", 1, "[room1,room2]")
    out = {"root": root, "c1": c1, "d1": d1, "c1-t": add_transfer(c1), "d1-t": add_transfer(d1)}
    out["c2"] = copy_as_seed(c1, root / "continual-seed2", 2, ignore=("transfer",))
    out["d2-t"] = copy_as_seed(out["d1-t"], alone / "drago-seed2", 2)
    out["d3-t"] = unfinish(copy_as_seed(out["d1-t"], alone / "drago-seed3", 3), episodes=1)
    return out


@pytest.fixture(scope="module")
def report(runs, tmp_path_factory) -> tuple[Path, Path]:
    return build_report([runs["c1"], runs["c2"], runs["d1"]], tmp_path_factory.mktemp("report"))


class TableParser(HTMLParser):
    """Collects every <table id=...> as rows of cell texts (header row first) and every <img> src."""

    def __init__(self):
        super().__init__()
        self.tables: dict[str, list[list[str]]] = {}
        self.images: list[str] = []
        self.body: dict[str, str] = {}
        self._table: list[list[str]] | None = None
        self._cell: list[str] | None = None

    def handle_starttag(self, tag, attrs):
        attrs = dict(attrs)
        if tag == "table":
            self._table = self.tables.setdefault(attrs.get("id", ""), [])
        elif tag == "tr" and self._table is not None:
            self._table.append([])
        elif tag in ("td", "th"):
            self._cell = []
        elif tag == "img":
            self.images.append(attrs.get("src", ""))
        elif tag == "body":
            self.body = attrs

    def handle_endtag(self, tag):
        if tag in ("td", "th") and self._cell is not None:
            self._table[-1].append("".join(self._cell))
            self._cell = None
        elif tag == "table":
            self._table = None

    def handle_data(self, data):
        if self._cell is not None:
            self._cell.append(data)


def parse(html_text: str) -> TableParser:
    parser = TableParser()
    parser.feed(html_text)
    return parser


def png(data: bytes) -> Image.Image:
    image = Image.open(io.BytesIO(data))
    assert image.format == "PNG"
    image.load()  # decodes every pixel: a truncated file fails here
    return image


def not_blank(image: Image.Image) -> bool:
    return image.convert("RGB").getcolors(maxcolors=1) is None  # None: more than one colour


def rows_by(table: list[list[str]], *keys: str) -> dict[tuple[str, ...], list[str]]:
    header, *rows = table
    index = [header.index(k) for k in keys]
    return {tuple(row[i] for i in index): dict(zip(header, row)) for row in rows}


def files_in(path: Path) -> dict[str, int]:
    return {str(p.relative_to(path)): p.stat().st_mtime_ns for p in sorted(path.rglob("*"))}


# ---------------------------------------------------------------------------------------------------
# per-cell scores and the heatmap figure
# ---------------------------------------------------------------------------------------------------
def test_cell_scores_average_each_cells_twelve_transitions():
    data = grid_transitions()
    # A score that differs per cell and per (heading, action): the cell's mean is known in closed form.
    score = data.cells[:, 0] + 100.0 * data.cells[:, 1] + data.headings * 3 + data.action_idx
    cells = cell_scores(score)
    assert cells.shape == (SIZE, SIZE)
    for x, y in traversable_cells():
        assert cells[y, x] == pytest.approx(x + 100 * y + np.mean([3 * d + a for d in range(4) for a in range(3)]))
    walls = np.array([[not is_traversable((x, y)) for x in range(SIZE)] for y in range(SIZE)])
    assert np.isnan(cells[walls]).all() and np.isfinite(cells[~walls]).all()
    # One diverged prediction makes its cell NaN, never a mean of the other eleven.
    broken = score.astype(float)
    broken[np.flatnonzero((data.cells == (1, 1)).all(1))[5]] = np.nan
    assert np.isnan(cell_scores(broken)[1, 1]) and np.isfinite(cell_scores(broken)[1, 2])
    with pytest.raises(ValueError, match="one per grid transition"):
        cell_scores(score[:-1])


@pytest.mark.slow
def test_heatmap_png_draws_methods_by_stages(runs):
    maps = run_cell_scores(runs["c1"])
    assert [(c.stage, c.task) for c, _ in maps] == [(1, "room1"), (2, "room2")]
    diverged = maps[1][1].copy()
    diverged[1, 1] = np.nan
    panels = {"continual": {c.stage: StageMaps(c.task, [m, m]) for c, m in maps},
              "drago": {1: StageMaps("room2", [diverged])}}
    image = png(heatmap_png(panels))
    assert image.width > image.height > 200 and not_blank(image)
    with pytest.raises(ValueError, match="at least one panel"):
        heatmap_png({})


# ---------------------------------------------------------------------------------------------------
# the report
# ---------------------------------------------------------------------------------------------------
@pytest.mark.slow
def test_report_on_partial_results(runs, report):
    html_path, md_path = report
    page = parse(html_path.read_text())
    assert set(page.tables) == {f"table-{key}" for key in TABLES}

    table = rows_by(page.tables["table-runs"], "method", "seed")
    assert table[("continual", "1")]["complete"] == "yes" and table[("continual", "1")]["tasks done"] == "2/2"
    assert table[("continual", "2")]["complete"] == "no" and table[("continual", "2")]["tasks done"] == "1/2"
    assert table[("drago", "1")]["complete"] == "yes" and table[("drago", "1")]["tasks done"] == "1/1"
    # Env steps over the finished tasks (200 a task here; no reviewer in a first task).
    assert [(table[key]["learner env steps"], table[key]["env steps"]) for key in (("continual", "1"),
            ("continual", "2"), ("drago", "1"))] == [("400", "400"), ("200", "200"), ("200", "200")]

    returns = rows_by(page.tables["table-returns"], "method", "task")
    assert set(returns) == {("continual", "room1"), ("continual", "room2"), ("drago", "room1")}
    assert returns[("continual", "room1")]["seeds"] == "2" and returns[("continual", "room2")]["seeds"] == "1"
    # Two seeds: mean ± std [CI]; one seed: the bare value.
    number = r"-?\d\.\d\d"
    assert re.fullmatch(rf"{number} ± {number} \[{number}, {number}\]",
                        returns[("continual", "room1")]["fraction of optimum"])
    assert re.fullmatch(number, returns[("continual", "room2")]["fraction of optimum"])

    coverage = rows_by(page.tables["table-coverage"], "method", "after stage")
    assert {k: v["seeds"] for k, v in coverage.items()} == {
        ("continual", "1: room1"): "2", ("continual", "2: room2"): "1", ("drago", "1: room1"): "1"}
    truth = {(r["stage"], r["room"]): r["accuracy"] for r in coverage_of_run(runs["c1"])}
    assert coverage[("continual", "2: room2")]["room1"] == f"{truth[(2, 'room1')]:.2f}"

    # Runs are grouped by how many stages they finished: T = 1 has no forgetting to show.
    metrics = rows_by(page.tables["table-metrics"], "method", "stages T")
    assert set(metrics) == {("continual", "2"), ("continual", "1"), ("drago", "1")}
    assert metrics[("continual", "1")]["BWT"] == "–"
    expected_bwt = truth[(2, "room1")] - truth[(1, "room1")]
    assert metrics[("continual", "2")]["BWT"] == f"{expected_bwt:.2f}"

    # Zero-shot planning with each stage's model: the evaluation's own numbers, paper cases starred.
    zero_shot = rows_by(page.tables["table-zero-shot"], "method", "after stage")
    assert {k: v["seeds"] for k, v in zero_shot.items()} == {k: v["seeds"] for k, v in coverage.items()}
    planned = {(r["stage"], r["task"]): r["fraction"] for r in zero_shot_matrix(runs["c1"])}
    assert zero_shot[("continual", "2: room2")]["room1to2"] == f"{planned[(2, 'room1to2')]:.2f} *"
    zero_metrics = rows_by(page.tables["table-zero-shot-metrics"], "method", "stages T")
    assert zero_metrics[("continual", "2")]["BWT"] == f"{planned[(2, 'room1')] - planned[(1, 'room1')]:.2f}"

    md = md_path.read_text()
    missing = md.split("## Missing", 1)[1]
    assert f"{runs['c2']} (continual, seed 2): incomplete, 1 of 2 tasks finished; not reached: room2" in missing
    assert "drago: 1 seed(s) (1) against 2 for continual" in missing
    assert "drago: room2 not in its runs' task sequence" in missing
    assert "continual: room2 finished by 1 of 2 runs" in missing
    assert len(page.images) == 2 and all(src.startswith("data:image/png;base64,") for src in page.images)


@pytest.mark.slow
def test_markdown_has_the_same_tables_and_figures(report):
    html_path, md_path = report
    page = parse(html_path.read_text())
    lines = md_path.read_text().splitlines()
    for table in page.tables.values():
        for row in table:
            assert "| " + " | ".join(cell.replace("|", "\\|") for cell in row) + " |" in lines
    figures = re.findall(r"!\[[^]]*\]\(([^)]+)\)", "\n".join(lines))
    assert sorted(figures) == ["curves.png", "heatmap.png"]
    embedded = sorted(base64.b64decode(src.split(",", 1)[1]) for src in page.images)
    assert embedded == sorted((md_path.parent / name).read_bytes() for name in figures)


@pytest.mark.slow
def test_report_writes_nothing_into_runs_and_reuses_fresh_coverage(runs, tmp_path):
    before = {name: files_in(path) for name, path in runs.items()}
    build_report(list(runs.values()), tmp_path / "a")
    assert {name: files_in(path) for name, path in runs.items()} == before

    # A coverage.csv that matches the checkpoints is used as is; an out-of-date one is not.
    run = tmp_path / "run"
    shutil.copytree(runs["c1"], run)
    rows = coverage_of_run(run)
    write_coverage_csv(rows, run / COVERAGE_FILE)
    _, md_path = build_report([run], tmp_path / "fresh")
    assert "coverage computed from the checkpoints" not in md_path.read_text()
    stale = "coverage.csv is older than or does not match its checkpoints"
    write_coverage_csv([r for r in rows if r["stage"] == 1], run / COVERAGE_FILE)
    _, md_path = build_report([run], tmp_path / "stale")
    text = md_path.read_text()
    assert stale in text and "| continual | 2: room2 | 1 |" in text
    # Written before the checkpoints (e.g. of an earlier run in the same directory): not trusted either.
    os.utime(write_coverage_csv(rows, run / COVERAGE_FILE), (0, 0))
    _, md_path = build_report([run], tmp_path / "older")
    assert stale in md_path.read_text()


@pytest.mark.slow
def test_find_run_dirs_takes_folders_but_not_what_lies_inside_a_run(runs, tmp_path):
    parent = runs["c1"].parent
    assert find_run_dirs([parent]) == sorted(runs.values())
    assert find_run_dirs([runs["d1"], parent]) == [runs["d1"], *sorted(set(runs.values()) - {runs["d1"]})]
    nested = tmp_path / "run"
    (nested / "transfer" / "room1to2-after1").mkdir(parents=True)
    for folder in (nested, nested / "transfer" / "room1to2-after1"):
        shutil.copy(runs["c1"] / "config.yaml", folder / "config.yaml")
    assert find_run_dirs([tmp_path]) == [nested]
    with pytest.raises(ReportError, match="holds none below it"):
        find_run_dirs([runs["c1"] / "checkpoints"])


def one_line_error(capsys, argv: list[str], fragment: str) -> None:
    assert cli.main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("drago: error: ") and fragment in err, err


@pytest.mark.slow
def test_cli_report(runs, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert cli.main(["report", str(runs["c1"].parent)]) == 0
    assert capsys.readouterr().out.splitlines() == ["wrote reports/report.html", "wrote reports/report.md"]
    assert len(rows_by(parse(Path("reports/report.html").read_text()).tables["table-runs"], "run directory")) == 3

    one_line_error(capsys, ["report"], "RUN_DIR")
    one_line_error(capsys, ["report", str(tmp_path / "nowhere")], "does not exist")
    one_line_error(capsys, ["report", str(runs["c1"] / "checkpoints")], "no config.yaml")
    one_line_error(capsys, ["report", str(runs["c1"] / "config.yaml")], "no config.yaml")
    broken = tmp_path / "broken"
    broken.mkdir()
    shutil.copy(runs["c1"] / "config.yaml", broken / "config.yaml")
    (broken / "summary.json").write_text("{not json")
    one_line_error(capsys, ["report", str(broken)], "summary.json is not readable JSON")
    (broken / "summary.json").unlink()
    (broken / "eval.csv").write_text("a,b\n1,2\n")
    one_line_error(capsys, ["report", str(runs["c1"]), str(broken)], "eval.csv lacks the column(s)")
    one_line_error(capsys, ["report", str(runs["c1"]), "--out", str(runs["c1"] / "config.yaml")],
                   "cannot write the report")


# ---------------------------------------------------------------------------------------------------
# transfers and DeepMind Control runs
# ---------------------------------------------------------------------------------------------------
@pytest.mark.slow
def test_report_has_a_transfer_section(transfers, tmp_path):
    t = transfers
    # The folder gives the sequence runs (their transfers are found inside them); transfer directories
    # given directly join them, one of them twice (also found inside its run), counted once.
    # Smoke learners never reach the sparse goal; drago seed 2 is given one episode that did (5 steps on it).
    with (t["d2-t"] / "train.csv").open(newline="") as handle:
        reader = csv.DictReader(handle)
        columns, rows = reader.fieldnames, list(reader)
    rows[1]["episode_reward"] = "5.0"
    with (t["d2-t"] / "train.csv").open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=columns)
        writer.writeheader()
        writer.writerows(rows)
    html_path, md_path = build_report([t["root"], t["d2-t"], t["d3-t"], t["d1-t"]], tmp_path / "report")
    page = parse(html_path.read_text())
    # DRAGO's runs finished room 1 before room 2: what its reviewer was paid in room 2 has a table.
    assert set(page.tables) == {f"table-{key}" for key in (*TABLES, "reviewer-pay", *TRANSFER_TABLES)}

    # Transfer runs are no continual runs of their method.
    runs = rows_by(page.tables["table-runs"], "method", "seed")
    assert set(runs) == {("continual", "1"), ("continual", "2"), ("drago", "1")}
    assert {row["tasks done"] for row in runs.values()} == {"2/2"}
    assert set(rows_by(page.tables["table-returns"], "method", "task")) == {
        (m, task) for m in ("continual", "drago") for task in ("room1", "room2")}

    def summary(transfer: Path) -> dict:
        return json.loads((transfer / "summary.json").read_text())["transfer"]["few_shot"]

    number = r"-?\d\.\d\d"
    episodes = rows_by(page.tables["table-transfer-episodes"], "case", "method")
    assert set(episodes) == {("room1to2 after 2", "continual"), ("room1to2 after 2", "drago")}
    continual, drago = episodes[("room1to2 after 2", "continual")], episodes[("room1to2 after 2", "drago")]
    point = summary(t["c1-t"])["equal_episodes"]
    assert (continual["seeds"], continual["learner episodes"], continual["total env steps"], continual["optimum"]) == (
        "1", "2", "200", "88.0")
    assert continual["fraction of optimum"] == f"{point['fraction_of_optimal']:.2f}"
    assert continual["return"] == f"{point['return']:.2f}"
    # Seeds 1 and 2 of drago finished (seed 3 has not reached episode 2); its reviewer doubles the env steps.
    assert (drago["seeds"], drago["learner episodes"], drago["total env steps"]) == ("2", "2", "400")
    assert re.fullmatch(rf"{number} ± {number} \[{number}, {number}\]", drago["fraction of optimum"])

    # At equal env steps drago is read after one learner episode, seed 3 (unfinished) included.
    steps = rows_by(page.tables["table-transfer-env-steps"], "case", "method")
    continual, drago = steps[("room1to2 after 2", "continual")], steps[("room1to2 after 2", "drago")]
    assert (continual["seeds"], continual["learner episodes"], continual["total env steps"]) == ("1", "2", "200")
    assert (drago["seeds"], drago["learner episodes"], drago["total env steps"]) == ("3", "1", "200")
    assert drago["fraction of optimum"].startswith(f"{summary(t['d1-t'])['equal_env_steps']['fraction_of_optimal']:.2f}")

    # The learners' own episodes, by hand from train.csv; drago seed 3 has not played both episodes yet.
    def own(transfer: Path) -> list[float]:
        with (transfer / "train.csv").open(newline="") as handle:
            return [float(r["episode_reward"]) for r in csv.DictReader(handle)]

    training = rows_by(page.tables["table-transfer-training"], "case", "method")
    continual, drago = training[("room1to2 after 2", "continual")], training[("room1to2 after 2", "drago")]
    c1 = own(t["c1-t"])
    assert len(c1) == 2 and (continual["seeds"], continual["learner episodes"]) == ("1", "2")
    assert continual["mean episode return"] == f"{np.mean(c1):.2f}"
    assert continual["episodes with a positive return"] == f"{sum(r > 0 for r in c1):.2f}"
    assert drago["seeds"] == "2" and len(own(t["d3-t"])) == 1
    assert own(t["d1-t"]) == [0.0, 0.0] and own(t["d2-t"]) == [0.0, 5.0]
    assert drago["mean episode return"].startswith("1.25 ± 1.77")  # seeds' means 0 and 2.5
    assert drago["episodes with a positive return"].startswith("0.50 ± 0.71")
    assert json.loads((t["c1-t"] / "summary.json").read_text())["transfer"]["training"] == {
        "episodes": 2, "mean_return": np.mean(c1), "positive_episodes": sum(r > 0 for r in c1)}

    md = md_path.read_text()
    missing = md.split("## Missing", 1)[1]
    assert (f"{t['d3-t']} (drago, seed 3, room1to2 after 2): unfinished, 1 of 2 learner episodes evaluated; "
            f"no few-shot score at equal episodes yet") in missing
    assert "continual: no transfer room1to2 after 2 for seed(s) 2" in missing
    assert "relearning" not in md  # test tasks only: no return matrix of training tasks to speak of
    assert "drago: 1 seed(s) (1) against 2 for continual" in missing

    # Figures: the sequence curves, the heatmap and the transfer curves (learner and total env steps).
    figures = re.findall(r"!\[[^]]*\]\(([^)]+)\)", md)
    assert sorted(figures) == ["curves.png", "heatmap.png", "reviewer-pay.png", "reviewer-reward.png",
                               "transfer-curves.png", "visitation.png"]  # drago runs: a reviewer
    assert len(page.images) == 6 and all(src.startswith("data:image/png;base64,") for src in page.images)
    image = png((md_path.parent / "transfer-curves.png").read_bytes())
    assert image.height > 300 and not_blank(image)
    for table in page.tables.values():
        for row in table:
            assert "| " + " | ".join(cell.replace("|", "\\|") for cell in row) + " |" in md.splitlines()

    # A transfer directory alone is a report of its own: no sequence run, one transfer row.
    html_path, md_path = build_report([t["d2-t"]], tmp_path / "alone")
    page = parse(html_path.read_text())
    assert set(page.tables) == {f"table-{key}" for key in TRANSFER_TABLES}  # the other tables: "no data"
    alone = rows_by(page.tables["table-transfer-episodes"], "case", "method")
    assert list(alone) == [("room1to2 after 2", "drago")] and alone[("room1to2 after 2", "drago")]["seeds"] == "1"
    assert "## Transfer learning curves" in md_path.read_text()


def test_dmc_runs_get_learning_curves_of_their_raw_return(tmp_path):
    pytest.importorskip("dm_control")
    run = tmp_path / "cheetah"
    assert cli.main(["train", "smoke", "--method", "continual", "--out", str(run), "--no-progress",
                     "train.tensorboard=false", "env.domain=cheetah", "env.tasks=[cheetah-run]", "env.action_repeat=4",
                     "env.episode_length=20", "train.steps_per_task=40", "agent.seed_steps=20", "agent.batch_size=16",
                     "train.eval_freq=80", "train.checkpoint_freq=80", "train.updates_per_episode=2",
                     "train.heldout_episodes=0"]) == 0
    with (run / "eval.csv").open(newline="") as handle:
        rows = list(csv.DictReader(handle))
    assert rows and not any(r.get("fraction_of_optimal") for r in rows)
    html_path, md_path = build_report([run], tmp_path / "report")
    md = md_path.read_text()
    assert "![Learning curves](curves.png)" in md and "raw return" in md
    page = parse(html_path.read_text())
    assert len(page.images) == 1 and not_blank(png((md_path.parent / "curves.png").read_bytes()))


# ---------------------------------------------------------------------------------------------------
# in a real browser
# ---------------------------------------------------------------------------------------------------
CHROMIUM = shutil.which("chromium")


@pytest.mark.slow
@pytest.mark.skipif(CHROMIUM is None, reason="no `chromium` on PATH (scripts/setup.sh installs Debian's package "
                                              "where apt-get and root or sudo are available)")
def test_report_renders_in_headless_chromium(report, tmp_path):
    html_path, _ = report
    browser = [CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars",
               f"--user-data-dir={tmp_path / 'profile'}", "--virtual-time-budget=5000"]
    url = html_path.resolve().as_uri()
    dom = subprocess.run([*browser, "--dump-dom", url], capture_output=True, text=True, timeout=120, check=True).stdout
    page = parse(dom)
    assert {f"table-{key}" for key in TABLES} <= set(page.tables)
    assert page.tables["table-runs"][0][:2] == ["method", "seed"] and len(page.tables["table-runs"]) == 4
    # Set by the page's own script on window load: every <img> decoded and has a size.
    assert len(page.images) == 2
    assert page.body.get("data-images-total") == "2" and page.body.get("data-images-loaded") == "2"
    for src in page.images:
        assert src.startswith("data:image/png;base64,")
        assert not_blank(png(base64.b64decode(src.split(",", 1)[1])))

    shot = tmp_path / "shot.png"
    subprocess.run([*browser, f"--screenshot={shot}", "--window-size=1280,2000", url],
                   capture_output=True, timeout=120, check=True)
    image = png(shot.read_bytes())
    assert image.size == (1280, 2000) and not_blank(image)


@pytest.mark.slow
def test_relearning_transfers_give_continual_metrics_of_returns(runs, tmp_path):
    run = tmp_path / "continual-seed1"
    shutil.copytree(runs["c1"], run, ignore=shutil.ignore_patterns("transfer"))
    score = {}
    for task in ("room1", "room2"):
        for after in (1, 2):
            assert cli.main(["transfer", str(run), "--no-progress", "--task", task, "--after", str(after),
                             "--episodes", "1"]) == 0
            block = json.loads((run / "transfer" / f"{task}-after{after}" / "summary.json").read_text())
            score[(after, task)] = block["transfer"]["few_shot"]["equal_episodes"]["fraction_of_optimal"]
    html_path, _ = build_report([run], tmp_path / "report")
    table = rows_by(parse(html_path.read_text()).tables["table-relearning-metrics"], "method", "stages T")
    # R[i][j]: room j relearned from the world model after stage i (GEM ACC and BWT, spec of issue 4).
    acc = (score[(2, "room1")] + score[(2, "room2")]) / 2
    bwt = score[(2, "room1")] - score[(1, "room1")]
    assert (table[("continual", "2")]["ACC"], table[("continual", "2")]["BWT"]) == (f"{acc:.2f}", f"{bwt:.2f}")

    # Without room 2 relearned after stage 1 the matrix stops at T = 1, and the report says what is lacking.
    shutil.rmtree(run / "transfer" / "room2-after1")
    html_path, md_path = build_report([run], tmp_path / "report")
    table = rows_by(parse(html_path.read_text()).tables["table-relearning-metrics"], "method", "stages T")
    assert set(table) == {("continual", "1")} and table[("continual", "1")]["BWT"] == "–"
    assert "relearning matrix stops at T = 1; it lacks room2 after 1" in md_path.read_text()


@pytest.mark.slow
def test_forward_transfer_against_scratch_by_hand(runs, tmp_path):
    """A `scratch` reference at 0.5 of the optimum throughout: FT = (AUC - 0.5) / (1 - 0.5) per room."""
    reference = tmp_path / "scratch-seed1"
    shutil.copytree(runs["c1"], reference, ignore=shutil.ignore_patterns("transfer"))
    config = yaml.safe_load((reference / "config.yaml").read_text())
    config["method"]["name"] = "scratch"
    (reference / "config.yaml").write_text(yaml.safe_dump(config, sort_keys=False))
    with (reference / "eval.csv").open(newline="") as handle:
        reader = csv.DictReader(handle)
        columns, rows = reader.fieldnames, list(reader)
    with (reference / "eval.csv").open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=columns)
        writer.writeheader()
        writer.writerows(dict(r, fraction_of_optimal="0.5") for r in rows)

    expected = {}
    for room in ("room1", "room2"):
        y = [float(r["fraction_of_optimal"]) for r in rows if r["task"] == room]
        auc = (sum(y) - (y[0] + y[-1]) / 2) / (len(y) - 1)  # trapezoid on [0, 1]
        expected[room] = (auc - 0.5) / 0.5
    html_path, _ = build_report([runs["c1"], reference], tmp_path / "report")
    table = rows_by(parse(html_path.read_text()).tables["table-forward-transfer"], "method")
    assert set(table) == {("continual",)}
    row = table[("continual",)]
    assert (row["room1"], row["room2"]) == (f"{expected['room1']:.2f}", f"{expected['room2']:.2f}")
    assert row["mean"] == f"{(expected['room1'] + expected['room2']) / 2:.2f}"

    # Without `scratch` runs there is no reference: no table, and the report says why.
    _, md_path = build_report([runs["c1"]], tmp_path / "alone")
    assert "Forward transfer (Continual World)" not in md_path.read_text()
    assert "needs `scratch` runs as the single-task reference" in md_path.read_text()


@pytest.mark.slow
def test_report_reuses_a_fresh_zero_shot_csv_made_with_the_defaults(runs, tmp_path):
    run = tmp_path / "run"
    shutil.copytree(runs["c1"], run)
    write_zero_shot_csv(zero_shot_matrix(run), run / ZERO_SHOT_FILE)
    _, md_path = build_report([run], tmp_path / "fresh")
    assert "zero-shot returns computed from the checkpoints" not in md_path.read_text()
    write_zero_shot_csv(zero_shot_matrix(run, episodes=1), run / ZERO_SHOT_FILE)  # not the report's numbers
    _, md_path = build_report([run], tmp_path / "other")
    assert "made with other tasks, episodes, horizon or epsilon" in md_path.read_text()
    write_zero_shot_csv(zero_shot_matrix(run, epsilon=0), run / ZERO_SHOT_FILE)  # deterministic: not the default
    _, md_path = build_report([run], tmp_path / "deterministic")
    assert "made with other tasks, episodes, horizon or epsilon" in md_path.read_text()

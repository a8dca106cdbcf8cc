"""Run records and studies that continue from them (docs: Reproducing the paper, "Studies that outlive the
machine"): a finished unit is one small file, and the same study command on another machine, holding only
the records folder, skips what is recorded with the same protocol and runs what is not."""

from __future__ import annotations

import gzip
import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest

from drago import cli
from drago.report.runs import ReportError, opened_runs
from drago.study.local import run_study
from drago.study.plan import DONE, START, format_duration, plan_study
from drago.training.records import RECORD_VERSION, RecordError, read_record, write_record

METHODS = ("continual", "scratch")
TINY = ["train.steps_per_task=200", "agent.seed_steps=100", "train.checkpoint_freq=100", "train.tensorboard=false",
        "agent.tdmpc.mlp_dim=16", "agent.batch_size=16", "agent.tdmpc.iterations=1", "agent.tdmpc.num_samples=8", "agent.tdmpc.num_elites=2",
        "train.threads=1"]
REPORT_FILES = ("report.md", "report.html", "transfers.csv", "transfers.md")


def plan(out: Path, records: Path, *extra: str, methods=METHODS):
    return plan_study("smoke", methods, [1], out=out, overrides=[*TINY, *extra], transfer_episodes=1, records=records)


def report_bytes(out: Path) -> dict[str, bytes]:
    return {name: (out / "report" / name).read_bytes() for name in REPORT_FILES}


@pytest.fixture(scope="module")
def recorded(tmp_path_factory) -> tuple[Path, Path]:
    """A finished two-method study with a records folder: (study folder, records folder)."""
    root = tmp_path_factory.mktemp("recorded")
    here = Path.cwd()
    os.chdir(root)  # relative paths, as a study committed to a repository is run from its root
    try:
        result = run_study(plan(Path("study"), Path("records")), echo=lambda line: None, in_process=cli.main)
    finally:
        os.chdir(here)
    assert result.ok, result.summary_line()
    return root / "study", root / "records"


@pytest.mark.slow
def test_each_finished_unit_is_one_small_record_without_binary_state(recorded):
    out, records = recorded
    paths = sorted(records.rglob("*.json.gz"))
    assert [p.relative_to(records).as_posix() for p in paths] == ["continual/seed1.json.gz", "scratch/seed1.json.gz"]
    for path in paths:
        record = read_record(path)
        files = record["files"]
        assert {"config.yaml", "summary.json", "eval.csv", "train.csv", "coverage.csv", "zero_shot.csv",
                "cells.json"} <= set(files)
        assert sum(name.startswith("transfer/") and name.endswith("/summary.json") for name in files) == 4
        assert not any(name.endswith((".pt", ".npz")) or name.startswith(("checkpoints/", "tb/")) for name in files)
        assert record["provenance"]["threads"] == 1 and record["provenance"]["torch"]
        assert "train.threads" not in record["protocol"]["run"] and "agent.tdmpc.precision" not in record["protocol"]["run"]
        # settings added since records exist stay out at their neutral default: older records keep their digest
        assert "method.options" not in record["protocol"]["run"]
        assert path.stat().st_size < 200_000


@pytest.mark.slow
def test_a_fresh_machine_with_only_the_records_skips_every_unit_and_writes_the_same_report(recorded, tmp_path,
                                                                                           monkeypatch):
    out, records = recorded
    shutil.copytree(records, tmp_path / "clone" / "records")
    monkeypatch.chdir(tmp_path / "clone")
    again = plan(Path("study"), Path("records"))
    assert all(job.state == DONE and job.recorded for job in [*again.runs, *again.transfers])
    assert not again.record_jobs
    lines = []
    result = run_study(again, echo=lines.append, in_process=cli.main)
    assert result.ok and not result.finished, lines
    assert not (tmp_path / "clone" / "study" / "continual").exists()  # nothing was trained
    assert report_bytes(tmp_path / "clone" / "study") == report_bytes(out)


@pytest.mark.slow
def test_a_changed_setting_reruns_exactly_the_units_it_changed(recorded, tmp_path):
    out, records = recorded
    mine = tmp_path / "records"
    shutil.copytree(records, mine)
    # scratch is studied again with another planner horizon: its record is replaced, continual's is untouched
    result = run_study(plan(tmp_path / "other", mine, "agent.tdmpc.horizon=2", methods=("scratch",)), echo=lambda line: None,
                       in_process=cli.main)
    assert result.ok
    assert read_record(mine / "scratch" / "seed1.json.gz")["protocol"]["run"]["agent.tdmpc.horizon"] == 2
    assert (mine / "continual" / "seed1.json.gz").read_bytes() == (records / "continual" / "seed1.json.gz").read_bytes()
    # the original study now has one unit to run again, and says why
    again = plan(tmp_path / "again", mine)
    states = {job.label: job.state for job in again.runs}
    assert states == {"continual seed1": DONE, "scratch seed1": START}
    assert [job.label for job in again.record_jobs] == ["scratch seed1 record"]
    assert any("agent.tdmpc.horizon: 2 recorded, 3 now" in note for note in again.notes), again.notes


@pytest.mark.slow
def test_a_corrupt_or_foreign_record_is_one_line_and_not_used(recorded, tmp_path, capsys):
    _, records = recorded
    mine = tmp_path / "records"
    shutil.copytree(records, mine)
    corrupt = mine / "continual" / "seed1.json.gz"
    corrupt.write_bytes(corrupt.read_bytes()[:200])
    foreign = mine / "scratch" / "seed1.json.gz"
    record = read_record(foreign)
    write_record({**record, "version": RECORD_VERSION + 1}, foreign)
    for path, why in ((corrupt, "is corrupt"), (foreign, f"has format version {RECORD_VERSION + 1}")):
        with pytest.raises(RecordError, match=why) as err:
            read_record(path)
        assert "\n" not in str(err.value)
        assert cli.main(["report", str(path), "--out", str(tmp_path / "r")]) == 2
        error = capsys.readouterr().err
        assert error.count("\n") == 1 and why in error
    again = plan(tmp_path / "study", mine)
    assert all(job.state == START and not job.recorded for job in again.runs)
    notes = " ".join(again.notes)
    assert "is corrupt" in notes and f"format version {RECORD_VERSION + 1}" in notes
    not_json = mine / "x.json.gz"
    not_json.write_bytes(gzip.compress(b"[1, 2]"))
    with pytest.raises(RecordError, match="not a drago run record"):
        read_record(not_json)


@pytest.mark.slow
def test_a_record_cannot_write_outside_its_view(recorded, tmp_path):
    _, records = recorded
    record = read_record(records / "continual" / "seed1.json.gz")
    evil = tmp_path / "evil.json.gz"
    write_record({**record, "files": {**record["files"], "../escaped.txt": "x"}}, evil)
    with pytest.raises(RecordError, match="outside its run directory"), opened_runs([evil]):
        pass
    assert not (tmp_path / "escaped.txt").exists()


@pytest.mark.slow
def test_records_and_run_directories_give_the_same_report_tables(recorded, tmp_path):
    out, records = recorded
    assert cli.main(["report", str(out / "continual" / "seed1"), str(out / "scratch" / "seed1"),
                     "--out", str(tmp_path / "dirs")]) == 0
    assert cli.main(["report", str(records), "--out", str(tmp_path / "recs")]) == 0
    dirs = (tmp_path / "dirs" / "report.md").read_text().splitlines()
    recs = (tmp_path / "recs" / "report.md").read_text().splitlines()
    assert len(dirs) == len(recs)
    differ = [(a, b) for a, b in zip(dirs, recs) if a != b]
    # only the page's provenance line and the runs' names differ
    assert differ[0][0].startswith("Generated ") and differ[0][1].startswith("Built from 2 records")
    assert all(str(out) in a and str(records) in b for a, b in differ[1:]) and len(differ) == 3


@pytest.mark.slow
def test_status_counts_units_and_the_cpu_hours_left(recorded, tmp_path, capsys):
    out, records = recorded
    argv = ["study", "smoke", "--methods", *METHODS, "ewc", "--seeds", "1", "--out", str(tmp_path / "s"),
            "--records", str(records), "--transfer-episodes", "1", "--status", *TINY]
    assert cli.main(argv) == 0
    text = capsys.readouterr().out
    assert f"units:   2 recorded in {records}, 0 in progress here, 1 to do" in text
    assert "CPU-hours" in text and "left" in text


@pytest.mark.slow
def test_status_before_the_first_record_counts_from_the_finished_jobs(recorded, tmp_path):
    """A study whose units take hours each says what is left before any is recorded: a unit of a method none of
    whose runs has finished costs the mean finished run and, per transfer case, the mean finished transfer."""
    from drago.study.plan import records_status
    from drago.training.rundir import read_summary

    out, _ = recorded
    study = plan(out, tmp_path / "none-yet", methods=(*METHODS, "ewc"))
    def cpu(job) -> float:
        return sum(t["cpu_time_s"] for t in read_summary(job.directory)["tasks"])

    finished = [j for j in (*study.runs, *study.transfers) if j.state == DONE]
    runs = [cpu(j) for j in finished if j.kind == "run"]
    transfers = [cpu(j) for j in finished if j.kind == "transfer"]
    assert len(runs) == 2 and len(transfers) == 2 * len(study.cases)
    # continual and scratch have finished every job (only their records are left); ewc has started none
    left = np.mean(runs) + len(study.cases) * np.mean(transfers)
    cost = next(line for line in records_status(study) if line.startswith("  cost:"))
    assert cost.startswith(f"  cost:    about {left / 3600:.1f} CPU-hours ({format_duration(left)}) left before the "
                           "units' evaluations"), cost


def test_record_command_refuses_an_unfinished_run(tmp_path, capsys):
    run = tmp_path / "run"
    assert cli.main(["train", "smoke", "--out", str(run), "--no-progress", *TINY, "env.tasks=[room1]"]) == 0
    summary = json.loads((run / "summary.json").read_text())
    summary["complete"] = False
    (run / "summary.json").write_text(json.dumps(summary))
    assert cli.main(["record", str(run), "--out", str(tmp_path / "r.json.gz")]) == 2
    assert "has not finished every task" in capsys.readouterr().err
    with pytest.raises(ReportError):
        with opened_runs([tmp_path / "nothing-here"]):
            pass


@pytest.mark.slow
def test_with_records_a_finished_runs_transfers_and_record_come_before_new_runs(tmp_path, monkeypatch):
    started: list[str] = []

    def fake_main(argv: list[str]) -> int:
        started.append(argv[0])
        return cli.main(argv)

    result = run_study(plan(tmp_path / "s", tmp_path / "r"), echo=lambda line: None, in_process=fake_main)
    assert result.ok
    # one run, its four transfers and its record, then the next unit
    assert started == ["train", *["transfer"] * 4, "record", "train", *["transfer"] * 4, "record"]


@pytest.mark.slow
def test_a_record_reads_like_its_run_directory_from_python(recorded):
    import drago

    out, records = recorded
    record, run = drago.Record(records / "continual" / "seed1.json.gz"), drago.Run(out / "continual" / "seed1")
    assert record.config == run.config and record.tasks == run.tasks and record.complete
    assert record.metrics("eval", as_frame=False).keys() == run.metrics("eval", as_frame=False).keys()
    np.testing.assert_array_equal(record.metrics("eval", as_frame=False)["episode_reward"],
                                  run.metrics("eval", as_frame=False)["episode_reward"])
    assert len(record.transfers()) == 4 and record.evaluation("costs") and record.evaluation("components")
    assert record.provenance["cpu"] and record.protocol["digest"]
    with pytest.raises(drago.RunDirError, match="keeps no checkpoints"):
        record.world_model(1)
    folder = record.path
    del record
    import gc
    gc.collect()
    assert not folder.exists()


@pytest.mark.slow
def test_the_same_command_in_a_fresh_git_clone_skips_every_unit(recorded, tmp_path):
    """Done literally: a clone of this repository, the records folder copied into it, the study command run
    there by the clone's own code in a child process."""
    import subprocess
    import sys

    root = Path(__file__).resolve().parents[1]
    if not (root / ".git").exists():
        pytest.skip("not a git checkout: nothing to clone")
    out, records = recorded
    clone = tmp_path / "clone"
    done = subprocess.run(["git", "clone", "--quiet", "--no-hardlinks", str(root), str(clone)], capture_output=True,
                          text=True, timeout=120)
    if done.returncode != 0:
        pytest.skip(f"git clone failed here: {done.stderr.strip()[:200]}")
    shutil.copytree(records, clone / "records")
    argv = [sys.executable, "-m", "drago", "study", "smoke", "--methods", *METHODS, "--seeds", "1", "--out", "study",
            "--records", "records", "--transfer-episodes", "1", *TINY]
    env = {**os.environ, "PYTHONPATH": str(clone)}
    result = subprocess.run(argv, cwd=clone, env=env, capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stdout + result.stderr
    assert "2 units recorded (skipped), 0 to record" in result.stdout
    assert "study complete: 0 jobs run" in result.stdout
    assert report_bytes(clone / "study") == report_bytes(out)


def test_a_slurm_studys_report_job_records_the_units_before_its_report(tmp_path):
    from drago.study.slurm.submission import report_argv

    argv = report_argv(plan(tmp_path / "s", tmp_path / "r"))
    assert argv[argv.index("--records") + 1] == str(tmp_path / "r") and "--report-only" in argv


@pytest.mark.slow
def test_the_results_page_section_is_regenerated_from_the_records(recorded, tmp_path):
    """docs/make_grid_results.py: the data files, the records' report and the page's section, from records only."""
    import subprocess
    import sys

    _, records = recorded
    root = Path(__file__).resolve().parents[1]
    docs = tmp_path / "docs"
    (docs / "data").mkdir(parents=True)
    (docs / "data" / "sources.json").write_text("{}")
    (docs / "results.md").write_text("# Results\n\n<!-- grid-records:start -->\nold\n<!-- grid-records:end -->\n\nrest\n")
    done = subprocess.run([sys.executable, str(root / "docs" / "make_grid_results.py"), "--records", str(records),
                           "--preset", "smoke", "--docs", str(docs)], capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stdout + done.stderr
    page = (docs / "results.md").read_text()
    assert "\nold\n" not in page and page.endswith("\n\nrest\n")
    assert "**2 of 21 units recorded**" in page
    table = [line for line in page.splitlines() if line.startswith("| `")]
    # the smoke preset's four tasks at the test's steps_per_task=200, no reviewer
    assert any(line.startswith("| `continual` | 800 + 0 | rooms ") for line in table), table
    assert "| `ewc` | – | to do | to do | to do |" in table, table
    assert "pending: 0 and 1 of 3 seeds recorded" in page  # drago against continual: one seed of continual only
    rows = (docs / "data" / "grid_records_final.csv").read_text().splitlines()
    assert rows[0] == "method,seed,task,fraction_of_optimal,late_training_success" and len(rows) == 1 + 2 * 4
    assert all(0.0 <= float(row.split(",")[4]) <= 1.0 for row in rows[1:])  # share of late training episodes
    # which part forgot: room 1 after the second task, its own heads, through the records' swap test
    forgot = next(line for line in page.splitlines() if line.startswith("| dynamics, 1 step (share exact) |"))
    assert forgot.count("(1 seed)") == 2  # continual and the second recorded method, one seed each
    swap = (docs / "data" / "grid_records_swap.csv").read_text().splitlines()
    assert swap[0] == "method,seed,stage,task,saved,moved,refit,true_reward" and swap[1].split(",")[2:4] == ["2", "room1"]
    assert (docs / "grid-report" / "report.md").is_file() and not (docs / "grid-report" / "report.html").exists()
    sources = json.loads((docs / "data" / "sources.json").read_text())
    assert sources["grid_records_final.csv"]["units"] == 2 and sources["grid_records_final.csv"]["commit"]


@pytest.mark.slow
def test_eval_tables_read_a_records_recorded_evaluation(recorded, capsys):
    out, records = recorded
    record = records / "continual" / "seed1.json.gz"
    assert cli.main(["eval", "coverage", str(record)]) == 0
    from_record = capsys.readouterr().out
    assert cli.main(["eval", "coverage", str(out / "continual" / "seed1")]) == 0
    from_run = capsys.readouterr().out
    def cells(text: str) -> list[list[str]]:  # each stage's row without its first column (how the run is named)
        return [line.split()[1:] for line in text.splitlines() if line.split()[1:2] in (["1"], ["2"], ["3"], ["4"])]

    assert len(cells(from_record)) == 4 and cells(from_record) == cells(from_run)
    assert f"read coverage.csv from the record {record}" in from_record
    assert cli.main(["eval", "heldout", str(record)]) == 2  # a grid unit records no held-out retention
    assert "holds no retention.csv" in capsys.readouterr().err


@pytest.mark.slow
@pytest.mark.skipif(shutil.which("chromium") is None, reason="no `chromium` on PATH (scripts/setup.sh installs it)")
def test_the_report_screenshots_show_the_records_sections(recorded, tmp_path):
    """docs/make_report_screenshots.py: each chosen section of the records' report, drawn by a browser, cropped."""
    import subprocess
    import sys

    from PIL import Image

    _, records = recorded
    root = Path(__file__).resolve().parents[1]
    done = subprocess.run([sys.executable, str(root / "docs" / "make_report_screenshots.py"), "--records", str(records),
                           "--out", str(tmp_path)], capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stdout + done.stderr
    for name in ("report-records-top.png", "report-records-components.png"):
        image = np.asarray(Image.open(tmp_path / name).convert("L"))
        height, width = image.shape
        assert 600 < width < 2000 and 200 < height < 6000, (name, image.shape)
        assert (image < 128).mean() > 0.005  # text and figures drawn, not a blank page
        assert (image[-10:] > 250).all()  # cropped below the last section, not cut through it
    only = tmp_path / "only"
    only.mkdir()
    done = subprocess.run([sys.executable, str(root / "docs" / "make_report_screenshots.py"), "--records", str(records),
                           "--out", str(only), "--only", "report-records-top.png"], capture_output=True, text=True,
                          timeout=600)
    assert done.returncode == 0, done.stdout + done.stderr
    assert sorted(p.name for p in only.iterdir()) == ["report-records-top.png"]

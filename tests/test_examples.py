"""The example plug-in package (examples/drago-example), installed into a virtual environment of its own:
drago finds its method and its domain through entry points, trains them, resumes after a kill and reports.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import sysconfig
from pathlib import Path

import pytest
from helpers import QUIET, sigkill_in_task_two

# Every test here installs the example package into a virtual environment of its own.
pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[1]
EXAMPLE = ROOT / "examples" / "drago-example"


@pytest.fixture(scope="module")
def venv(tmp_path_factory) -> Path:
    """A new virtual environment that sees this one's packages (torch, drago) and has the example installed,
    as `pip install ./examples/drago-example` would do, without the network."""
    root = tmp_path_factory.mktemp("example-venv") / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(root)], check=True)
    site = next((root / "lib").glob("python*/site-packages"))
    # The packages of the environment running the tests, .pth files included (drago is installed editable).
    (site / "parent_environment.pth").write_text(f"import site; site.addsitedir({sysconfig.get_path('purelib')!r})\n")
    python = root / "bin" / "python"
    install = subprocess.run([str(python), "-m", "pip", "install", "--quiet", "--no-deps", "--no-build-isolation",
                              "--disable-pip-version-check", str(EXAMPLE)], capture_output=True, text=True)
    assert install.returncode == 0, install.stderr
    return root


def drago(venv: Path, *args: str, timeout: float = 300) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    return subprocess.run([str(venv / "bin" / "python"), "-m", "drago", *args], capture_output=True, text=True,
                          timeout=timeout, env=env)


def test_drago_lists_the_plugins_method_domain_and_preset_with_their_package(venv):
    listing = drago(venv, "list")
    assert listing.returncode == 0, listing.stderr
    assert "l2-anchor" in listing.stdout and "two-pendulums" in listing.stdout
    assert "pendulums-quick (package drago-example)" in listing.stdout
    assert "(package drago-example)" in next(line for line in listing.stdout.splitlines() if "l2-anchor" in line)
    assert "warning" not in listing.stderr


def test_the_plugins_preset_trains_by_name_with_the_plugins_own_setting(venv, tmp_path):
    run = tmp_path / "quick"
    trained = drago(venv, "train", "pendulums-quick", "--method", "l2-anchor", "--out", str(run), *QUIET,
                    "method.anchor_coef=10")
    assert trained.returncode == 0, trained.stdout + trained.stderr
    assert (run / "checkpoints" / "task2_spin.pt").is_file()
    written = (run / "config.yaml").read_text()
    assert "preset: pendulums-quick" in written and "anchor_coef: 10.0" in written
    listing = drago(venv, "list", "--settings")
    line = next(line for line in listing.stdout.splitlines() if "method.anchor_coef" in line)
    assert "float, l2-anchor only" in line and "100.0" in line
    typo = drago(venv, "train", "pendulums-quick", "--method", "l2-anchor", "--out", str(tmp_path / "typo"),
                 "method.anchor_cof=10")
    assert typo.returncode == 2 and "did you mean method.anchor_coef?" in typo.stderr
    assert not (tmp_path / "typo").exists()


def test_the_plugins_method_trains_resumes_after_a_kill_and_reports(venv, tmp_path):
    run = tmp_path / "anchor"
    # Killed in task 2, once its periodic checkpoint exists: the first task's anchor must survive the kill.
    code = sigkill_in_task_two(["smoke", "--method", "l2-anchor", *QUIET, "env.tasks=[room1,room2]"], run, tmp_path,
                               wait_s=240, drago=[str(venv / "bin" / "python"), "-m", "drago"])
    assert code == -signal.SIGKILL
    resumed = drago(venv, "resume", str(run), "--no-progress")
    assert resumed.returncode == 0, resumed.stdout + resumed.stderr
    report = drago(venv, "report", str(run), "--out", str(tmp_path / "report"))
    assert report.returncode == 0, report.stderr
    text = (tmp_path / "report" / "report.md").read_text()
    assert "l2-anchor" in text and "room2" in text


def test_the_plugins_domain_trains_a_two_task_sequence(venv, tmp_path):
    run = tmp_path / "pendulums"
    trained = drago(venv, "train", "smoke", "--method", "drago", "--out", str(run), *QUIET,
                    "env.domain=two-pendulums", "env.tasks=[swingup,spin]", "env.episode_length=50",
                    "train.steps_per_task=200", "agent.seed_steps=100", "train.heldout_episodes=1")
    assert trained.returncode == 0, trained.stdout + trained.stderr
    assert (run / "checkpoints" / "task2_spin.pt").is_file() and (run / "heldout" / "task2_spin.npz").is_file()

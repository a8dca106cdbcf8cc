"""Moving code does not change results: every method with both agent kinds writes the logs recorded before
(tests/golden_logs.py; docs: Design, "Changing code without changing results")."""

from __future__ import annotations

import json

import pytest

from golden_logs import GOLDEN, cases, digests, machine_key


def recorded() -> dict:
    return json.loads(GOLDEN.read_text()).get(machine_key(), {}) if GOLDEN.is_file() else {}


@pytest.mark.slow
@pytest.mark.parametrize("kind, method", cases())
def test_logs_are_byte_identical_to_the_recorded_ones(kind, method, tmp_path):
    golden = recorded()
    if not golden:
        pytest.skip(f"no golden logs recorded for {machine_key()}: `python tests/golden_logs.py` records them "
                    "(before a change, never after)")
    assert f"{kind}/{method}" in golden, f"{kind}/{method} has no golden logs: record them before changing code"
    assert digests(kind, method, tmp_path) == golden[f"{kind}/{method}"]


def test_every_method_is_covered():
    golden = recorded()
    if not golden:
        pytest.skip(f"no golden logs recorded for {machine_key()}")
    assert sorted(golden) == sorted(f"{kind}/{method}" for kind, method in cases())

"""The speed benchmark's matmul replay: it must replay exactly the matrix multiplies a call ran."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import torch

_PATH = Path(__file__).resolve().parents[1] / "benchmarks" / "bench_speed.py"
_SPEC = importlib.util.spec_from_file_location("bench_speed", _PATH)
bench = importlib.util.module_from_spec(_SPEC)
_SPEC.loader.exec_module(bench)


def _layer_step(layer: torch.nn.Linear, x: torch.Tensor, shared: torch.Tensor) -> torch.Tensor:
    """A linear layer's forward and backward (x needs a gradient: dx = dy W is a matmul too), then a bmm
    against a broadcast (stride-0) operand."""
    y = layer(x)
    y.sum().backward()
    return torch.bmm(y.detach().view(2, 2, 5), shared.expand(2, 5, 3))


def test_recorder_sees_forward_and_backward_matmuls_and_leaves_results_alone():
    torch.manual_seed(0)
    layer, x, shared = torch.nn.Linear(3, 5), torch.randn(4, 3, requires_grad=True), torch.randn(1, 5, 3)
    expected = _layer_step(layer, x, shared)
    layer.zero_grad()
    recorder = bench.record_matmuls(lambda: _layer_step(layer, x, shared))
    names = [str(func) for func, _, _ in recorder.calls]
    # forward addmm(bias, x, W^T); backward dx = dy W and dW = dy^T x; the bias gradient is a sum, not a matmul
    assert names == ["aten.addmm.default", "aten.mm.default", "aten.mm.default", "aten.bmm.default"]
    shapes = [[a[0] for a in layout if isinstance(a, tuple)] for _, layout, _ in recorder.calls]
    assert shapes[0] == [(5,), (4, 3), (3, 5)]
    assert sorted(shapes[1:3]) == [[(4, 5), (5, 3)], [(5, 4), (4, 3)]]
    assert recorder.calls[3][1][1][1] == (0, 3, 1)  # the broadcast operand keeps its zero stride
    torch.testing.assert_close(_layer_step(layer, x, shared), expected)


def test_replay_runs_the_same_matmuls_with_the_same_layouts():
    torch.manual_seed(0)
    layer, x, shared = torch.nn.Linear(3, 5), torch.randn(4, 3, requires_grad=True), torch.randn(1, 5, 3)
    recorder = bench.record_matmuls(lambda: _layer_step(layer, x, shared))
    replay = bench.record_matmuls(recorder.replay_fn())
    assert len(recorder.calls) == 4
    assert replay.calls == recorder.calls

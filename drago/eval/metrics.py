"""Continual-learning metrics from a performance matrix, under the names of the papers that define them.

The input is a matrix ``R`` of shape ``(stages, tasks)`` where ``R[i, j]`` is the performance on task
``j`` measured after training stage ``i`` (0-based: stage ``i`` ends after learning task ``i``). In this
project ``R`` holds the world model's exact-match coverage of room ``j`` after stage ``i``, or
few-shot returns. Task columns beyond the number of stages (tasks never trained, e.g. held out) are
ignored: every metric below speaks only of the tasks that were learned, as in the square ``T x T``
matrix of the papers. A partially finished run (fewer stages than planned tasks) is thus measured at
its last finished stage.

Two conventions are provided because papers report either:

* GEM (Lopez-Paz & Ranzato 2017): average accuracy ``ACC``, backward transfer ``BWT`` (negative when
  the learner forgets) and forward transfer ``FWT`` against a randomly initialised model;
* Continual World (Wołczyk et al. 2021): average performance at the end of the sequence (the same
  number as ``ACC``), forgetting (the same number as ``-BWT``) and forward transfer from the area
  under training curves against a single-task reference.

A matrix-only version of Continual World's forward transfer,
``mean_j (R[j, j] - ref[j]) / (1 - ref[j])``, is deliberately not offered: Continual World measures
transfer as a difference in *learning speed* (area under the curve during training); replacing the
area by end-of-training performance measures something else, and it is undefined exactly when the
single-task reference learns the task perfectly (``ref[j] = 1``), which is the normal case for
coverage of a small room. Use :func:`cw_forward_transfer` on training curves instead.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

__all__ = [
    "gem_acc",
    "gem_bwt",
    "gem_fwt",
    "cw_average_performance",
    "cw_forgetting",
    "cw_forward_transfer",
    "continual_metrics",
]


def _matrix(R: Any, min_stages: int = 1) -> np.ndarray:
    """``R`` as a finite float ``(stages, tasks)`` array with a column for every learned task."""
    a = np.asarray(R, dtype=float)
    if a.ndim != 2:
        raise ValueError(
            f"R must be a 2-D (stages, tasks) matrix with R[i, j] = performance on task j after "
            f"stage i; got shape {a.shape}"
        )
    stages, tasks = a.shape
    if stages < min_stages:
        raise ValueError(
            f"this metric needs R with at least {min_stages} stage(s) (rows); got shape {a.shape}"
        )
    if tasks < stages:
        raise ValueError(
            f"R has {stages} stages but only {tasks} task columns; stage i learns task i, so give "
            f"at least one column per stage"
        )
    if not np.isfinite(a).all():
        bad = tuple(int(i) for i in np.argwhere(~np.isfinite(a))[0])
        raise ValueError(
            f"R has a non-finite value at {bad}; evaluate or drop the missing stage before "
            "computing metrics"
        )
    return a


def _baseline(random_baseline: Any, tasks: int) -> np.ndarray:
    """``random_baseline`` as a finite vector with one entry per task column of ``R``."""
    b = np.asarray(random_baseline, dtype=float)
    if b.ndim != 1 or b.shape[0] != tasks:
        raise ValueError(
            f"random_baseline must be a vector with one entry per task column of R ({tasks}); "
            f"got shape {b.shape}"
        )
    if not np.isfinite(b).all():
        raise ValueError("random_baseline has a non-finite value; evaluate the random model on every task")
    return b


def gem_acc(R: Any) -> float:
    """Average accuracy after the last stage: ``ACC = (1/T) sum_j R[T-1, j]``.

    Lopez-Paz & Ranzato 2017, "Gradient Episodic Memory for Continual Learning", §5 (eq. for ACC),
    with ``T`` the number of stages and ``j`` over the ``T`` learned tasks.
    """
    a = _matrix(R)
    T = a.shape[0]
    return float(a[T - 1, :T].mean())


def gem_bwt(R: Any) -> float:
    """Backward transfer: ``BWT = 1/(T-1) sum_{j<T-1} (R[T-1, j] - R[j, j])``.

    Lopez-Paz & Ranzato 2017, §5 (eq. for BWT): how much learning later tasks changed performance on
    earlier ones; negative values are forgetting. The last task is excluded since nothing was
    learned after it. Needs at least two stages.
    """
    a = _matrix(R, min_stages=2)
    T = a.shape[0]
    j = np.arange(T - 1)
    return float((a[T - 1, j] - a[j, j]).mean())


def gem_fwt(R: Any, random_baseline: Any) -> float:
    """Forward transfer: ``FWT = 1/(T-1) sum_{j>=1} (R[j-1, j] - b[j])``.

    Lopez-Paz & Ranzato 2017, §5 (eq. for FWT): performance on task ``j`` *before* training on it
    (after stage ``j-1``) relative to ``b[j]``, the performance of a randomly initialised model on
    task ``j``; positive values mean earlier tasks helped. ``random_baseline`` has one entry per task
    column of ``R``. Needs at least two stages.
    """
    a = _matrix(R, min_stages=2)
    b = _baseline(random_baseline, a.shape[1])
    T = a.shape[0]
    j = np.arange(1, T)
    return float((a[j - 1, j] - b[j]).mean())


def cw_average_performance(R: Any) -> float:
    """Average performance at the end of the sequence: ``P(T) = (1/T) sum_j R[T-1, j]``.

    Wołczyk et al. 2021, "Continual World: A Robotic Benchmark For Continual Reinforcement
    Learning", §3 (metrics: average performance ``P(t)`` taken at ``t = T``). The same number as
    :func:`gem_acc`; kept under this name so tables can follow either paper.
    """
    return gem_acc(R)


def cw_forgetting(R: Any) -> float:
    """Forgetting: ``F = 1/(T-1) sum_{j<T-1} (R[j, j] - R[T-1, j])``.

    Wołczyk et al. 2021, §3 (metrics: ``F_i = p_i(i·Δ) - p_i(T)``, performance right after learning
    task ``i`` minus at the end), averaged over the tasks that had later tasks after them. Positive
    values mean forgetting; equal to ``-gem_bwt(R)``. Needs at least two stages.
    """
    # Computed directly rather than as -gem_bwt so a forgetting-free run reads 0.0, not -0.0.
    a = _matrix(R, min_stages=2)
    T = a.shape[0]
    j = np.arange(T - 1)
    return float((a[j, j] - a[T - 1, j]).mean())


def _normalised_auc(y: np.ndarray) -> float:
    """Trapezoid area under ``y`` on a uniform grid rescaled to ``[0, 1]``: a mean of the curve."""
    return float((y.sum() - 0.5 * (y[0] + y[-1])) / (y.shape[0] - 1))


def cw_forward_transfer(curve: Any, reference_curve: Any, max_performance: float = 1.0) -> float:
    """Forward transfer of one task: ``FT = (AUC - AUC_ref) / (max_performance - AUC_ref)``.

    Wołczyk et al. 2021, §3 (metrics: ``FT_i = (AUC_i - AUC_i^b) / (1 - AUC_i^b)``), where
    ``AUC_i`` is the area under the task's performance curve during its training in the continual
    run and ``AUC_i^b`` the same for a reference trained on the task alone. Both curves are sampled
    on the same uniform grid over the task's training; the grid is rescaled to ``[0, 1]`` and the
    area taken with the trapezoid rule, so an AUC is a time-average of the performance on the
    curve's own scale. The denominator is the most the continual run could gain over the reference,
    so FT is 1 for a curve at ``max_performance`` throughout, 0 for a curve equal to the reference,
    negative when the continual learner is slower. Continual World uses success rates, so
    ``max_performance`` defaults to 1; pass the ceiling of another scale explicitly.
    """
    y = np.asarray(curve, dtype=float)
    ref = np.asarray(reference_curve, dtype=float)
    if y.ndim != 1 or y.shape != ref.shape:
        raise ValueError(
            f"curve and reference_curve must be 1-D on the same grid; got shapes {y.shape} and {ref.shape}"
        )
    if y.shape[0] < 2:
        raise ValueError(f"curves need at least 2 points to have an area; got {y.shape[0]}")
    if not (np.isfinite(y).all() and np.isfinite(ref).all()):
        raise ValueError("curve or reference_curve has a non-finite value; drop or fill missing evaluations")
    auc = _normalised_auc(y)
    auc_ref = _normalised_auc(ref)
    headroom = max_performance - auc_ref
    if headroom <= 0.0:
        raise ValueError(
            f"reference AUC {auc_ref:g} reaches max_performance {max_performance:g}, so forward "
            "transfer is undefined; check max_performance or the reference curve"
        )
    return float((auc - auc_ref) / headroom)


def continual_metrics(R: Any, random_baseline: Any = None) -> dict[str, float]:
    """All matrix metrics at once: ``acc``, ``bwt``, ``fwt`` (only with a baseline),
    ``average_performance`` and ``forgetting``.

    With a single stage there is no earlier task to forget or later task to transfer to, so
    ``bwt``, ``forgetting`` and ``fwt`` are NaN rather than an error: a one-task run still gets a row
    in a results table.
    """
    a = _matrix(R)
    single = a.shape[0] < 2
    out: dict[str, float] = {
        "acc": gem_acc(a),
        "bwt": math.nan if single else gem_bwt(a),
    }
    if random_baseline is not None:
        # Validated even for one stage so a malformed baseline is not hidden until a longer run.
        _baseline(random_baseline, a.shape[1])
        out["fwt"] = math.nan if single else gem_fwt(a, random_baseline)
    out["average_performance"] = cw_average_performance(a)
    out["forgetting"] = math.nan if single else cw_forgetting(a)
    return out

"""Statistics over seeds: interquartile mean and stratified bootstrap confidence intervals.

A handful of seeds per configuration is all RL experiments can usually afford, so a bare mean hides
how much of a difference between methods is noise. Following Agarwal et al. 2021, "Deep
Reinforcement Learning at the Edge of the Statistical Precipice" (NeurIPS; the ``rliable`` library),
results are reported as point estimates with 95% bootstrap intervals, and the interquartile mean (IQM)
is offered next to the mean because it is robust to one diverged seed yet, unlike the median, still
uses half of the runs.

Only numpy is used: the project does not depend on scipy, and the few pieces needed (a trimmed mean
and percentile bootstrap) are short enough to own.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = ["Summary", "iqm", "stratified_bootstrap_ci", "summarize", "aggregate"]

# Bootstrap replicates are drawn in blocks of at most this many resampled values, so a large
# (runs, tasks) array cannot allocate reps * runs * tasks numbers at once on a small machine.
_MAX_BLOCK_ELEMENTS = 1 << 22

# The share cut from each end for the IQM (Agarwal et al. 2021, §4: the middle 50% of the runs).
_IQM_CUT = 0.25


@dataclass(frozen=True)
class Summary:
    """One configuration's per-seed values condensed for a table.

    Kept as plain numbers (not a formatted string) so a report can sort, compare or re-format them.
    """

    n: int
    mean: float
    std: float
    iqm: float
    ci_low: float
    ci_high: float

    def format(self, digits: int = 2) -> str:
        """``"mean ± std [ci_low, ci_high]"``; ``"–"`` with no values; the bare value for one seed.

        A single seed has no spread to show, and printing ``± 0.00 [x, x]`` would suggest a
        certainty that one run cannot give.
        """
        if self.n == 0:
            return "–"
        if self.n == 1:
            return f"{self.mean:.{digits}f}"
        return (
            f"{self.mean:.{digits}f} ± {self.std:.{digits}f} "
            f"[{self.ci_low:.{digits}f}, {self.ci_high:.{digits}f}]"
        )


def iqm(values: Any, axis: int | None = None) -> float | np.ndarray:
    """Interquartile mean: the mean of the middle 50% of the values.

    This is ``scipy.stats.trim_mean(values, 0.25)`` re-implemented (Agarwal et al. 2021, §4): sort,
    drop ``int(0.25 * n)`` values from each end, average the rest. With fewer than four values nothing
    is dropped and the IQM equals the mean. Over the flattened array when ``axis`` is None (a float),
    otherwise along ``axis`` (an array). A NaN among the values makes the result NaN, as trimming would
    otherwise silently discard it.
    """
    a = np.asarray(values, dtype=float)
    if axis is None:
        a = a.reshape(-1)
        axis = 0
    elif a.ndim == 0:
        raise ValueError(f"iqm got a scalar but axis={axis}; pass an array or use axis=None")
    n = a.shape[axis]
    if n == 0:
        raise ValueError("iqm needs at least one value; got an empty array")
    cut = int(_IQM_CUT * n)
    ordered = np.sort(a, axis=axis)
    middle = np.take(ordered, np.arange(cut, n - cut), axis=axis)
    result = middle.mean(axis=axis)
    # np.sort moves NaNs to the end, where the trim could drop them and hide missing data.
    result = np.where(np.isnan(a).any(axis=axis), np.nan, result)
    if result.ndim == 0:
        return float(result)
    return result


def _as_runs_by_tasks(scores: Any) -> np.ndarray:
    """Validate ``scores`` and shape it ``(runs, tasks)``; a 1-D input is one task (one stratum)."""
    a = np.asarray(scores, dtype=float)
    if a.ndim == 1:
        # A missing seed in a 1-D list only shrinks the sample; dropping it keeps the rest usable.
        a = a[np.isfinite(a)][:, None]
    elif a.ndim == 2:
        if not np.isfinite(a).all():
            bad = tuple(int(i) for i in np.argwhere(~np.isfinite(a))[0])
            raise ValueError(
                f"scores has a non-finite value at {bad}; a (runs, tasks) array must be complete, "
                "so drop the run or fill the value first"
            )
    else:
        raise ValueError(f"scores must have shape (runs,) or (runs, tasks); got shape {a.shape}")
    if a.size == 0:
        raise ValueError(f"scores has no finite values (shape {np.shape(scores)}); pass at least one run")
    return a


def _apply_per_replicate(statistic: Callable[..., Any], block: np.ndarray) -> np.ndarray:
    """``statistic`` of each row of ``block`` (replicates, values), vectorised when it takes ``axis``.

    numpy reductions and :func:`iqm` take ``axis``; a user's plain function falls back to
    ``np.apply_along_axis`` so that any callable still works, only slower.
    """
    try:
        out = np.asarray(statistic(block, axis=1), dtype=float)
    except TypeError:
        out = np.asarray(np.apply_along_axis(statistic, 1, block), dtype=float)
    if out.shape != (block.shape[0],):
        raise ValueError(
            f"statistic must reduce each replicate to one number; got output shape {out.shape} "
            f"for {block.shape[0]} replicates"
        )
    return out


def stratified_bootstrap_ci(
    scores: Any,
    statistic: Callable[..., Any] = np.mean,
    reps: int = 2000,
    confidence: float = 0.95,
    seed: int = 0,
) -> tuple[float, float]:
    """Percentile bootstrap interval of ``statistic`` with the runs resampled within each task.

    ``scores`` has shape ``(runs,)`` or ``(runs, tasks)``. Each replicate draws ``runs`` rows with
    replacement independently for every task column (each task is a stratum, Agarwal et al. 2021,
    §4 / rliable's ``StratifiedBootstrap``), so every task keeps its share of the sample and the
    between-task differences, which are fixed by design rather than random, do not widen the
    interval. ``statistic`` is applied to each whole resampled array (flattened) and the interval is
    the ``(1 - confidence) / 2`` and ``(1 + confidence) / 2`` percentiles of the replicates.

    Deterministic for a given ``seed``. Non-finite entries of a 1-D input are dropped; a 2-D input
    must be complete (raises ``ValueError``), since dropping one cell would unbalance the strata.
    """
    if not 0.0 < confidence < 1.0:
        raise ValueError(f"confidence must lie strictly between 0 and 1; got {confidence}")
    if reps < 1:
        raise ValueError(f"reps must be at least 1; got {reps}")
    a = _as_runs_by_tasks(scores)
    runs, tasks = a.shape
    rng = np.random.default_rng(seed)
    columns = np.arange(tasks)
    block_reps = max(1, _MAX_BLOCK_ELEMENTS // a.size)
    replicates = np.empty(reps, dtype=float)
    for start in range(0, reps, block_reps):
        stop = min(reps, start + block_reps)
        rows = rng.integers(0, runs, size=(stop - start, runs, tasks))
        # Pairing each drawn row index with its own column keeps the draw inside that task's stratum.
        resampled = a[rows, columns]
        replicates[start:stop] = _apply_per_replicate(statistic, resampled.reshape(stop - start, -1))
    tail = 100.0 * (1.0 - confidence) / 2.0
    low, high = np.percentile(replicates, [tail, 100.0 - tail])
    return float(low), float(high)


def summarize(values: Any, reps: int = 2000, confidence: float = 0.95, seed: int = 0) -> Summary:
    """Mean, sample std, IQM and bootstrap CI of the mean of one configuration's per-seed values.

    Non-finite values (a crashed or unfinished seed) are dropped and ``n`` counts the kept ones, so a
    table shows how many seeds a number rests on. With no values everything is NaN; with one, the
    std is 0 and the interval collapses to the value, since one run cannot show any spread.
    """
    a = np.asarray(values, dtype=float)
    if a.ndim > 1:
        raise ValueError(f"summarize takes a 1-D collection of per-seed values; got shape {a.shape}")
    kept = a.reshape(-1)[np.isfinite(a.reshape(-1))]
    n = int(kept.size)
    if n == 0:
        nan = math.nan
        return Summary(n=0, mean=nan, std=nan, iqm=nan, ci_low=nan, ci_high=nan)
    mean = float(kept.mean())
    if n == 1:
        return Summary(n=1, mean=mean, std=0.0, iqm=mean, ci_low=mean, ci_high=mean)
    low, high = stratified_bootstrap_ci(kept, np.mean, reps=reps, confidence=confidence, seed=seed)
    return Summary(
        n=n,
        mean=mean,
        std=float(kept.std(ddof=1)),
        iqm=float(iqm(kept)),
        ci_low=low,
        ci_high=high,
    )


def aggregate(
    scores: Any, reps: int = 2000, confidence: float = 0.95, seed: int = 0
) -> dict[str, tuple[float, float, float]]:
    """rliable's aggregate metrics over a ``(runs, tasks)`` array: ``(point, ci_low, ci_high)`` each.

    Mean, IQM and median are taken over all values together (runs and tasks pooled), with a
    stratified bootstrap interval for each (Agarwal et al. 2021, §4-5). All three share the seed,
    so their intervals come from the same resampled arrays and stay comparable.
    """
    a = _as_runs_by_tasks(scores)
    statistics: dict[str, Callable[..., Any]] = {"mean": np.mean, "iqm": iqm, "median": np.median}
    result: dict[str, tuple[float, float, float]] = {}
    for name, statistic in statistics.items():
        point = float(np.asarray(statistic(a.reshape(1, -1), axis=1))[0])
        low, high = stratified_bootstrap_ci(a, statistic, reps=reps, confidence=confidence, seed=seed)
        result[name] = (point, low, high)
    return result

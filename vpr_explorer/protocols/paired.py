"""Numbers over splits: mean ± std, a 95% interval of the mean, and two sets of splits compared.

The paper and open-set protocols score R seeded random splits (``evaluation.draw_splits``);
every rate of a method is one value per split (``MethodRow.per_split``). Over those values:

* **summary** (``summary``): the finite values x₁ … xₙ (a split where the rate is
  undefined, e.g. the precision of nothing accepted, is NaN and left out); mean x̄; sample
  standard deviation s = √(Σ(xᵢ − x̄)²/(n − 1)) (ddof 1); the 95% interval of the mean by
  Student's t, x̄ ± t₀.₉₇₅,ₙ₋₁ · s/√n (``scipy.stats.t.ppf(0.975, n − 1)``). One value has
  no spread: s and the interval are NaN. A protocol of one deterministic run (traversal,
  database/queries) is n = 1. The interval is not cut to [0, 1]: with few splits it may pass
  a rate's ends (the t interval takes the per-split values as normal), which says as much.
* **paired** (``paired``), for two sets of numbers **on the same splits** (two methods of
  one run, or two runs whose splits are the same: ``evaluation.draw_splits`` draws them
  from the seed, the runs and the places alone, so two runs that agree on those share
  every split, whatever their descriptors, tolerance or cross-condition): the per-split
  differences dᵢ = aᵢ − bᵢ over the splits where both are finite; their mean d̄ (the
  difference of the means), their std s_d (ddof 1), the interval d̄ ± t₀.₉₇₅,ₙ₋₁ · s_d/√n,
  and the paired t-test t = d̄/(s_d/√n), two-sided p = 2·(1 − F_{n−1}(|t|))
  (``scipy.stats.ttest_rel``). When every difference is 0 the test is undefined (0/0):
  p is NaN and the comparison says **identical on every split**. When every split differs by
  the same non-zero amount, s_d = 0, t is infinite and p = 0 (scipy's answer too). Rates
  are fractions of query counts, so two differences that are equal in exact arithmetic may
  differ by float rounding (~1e-16): differences within ``EQUAL_TOLERANCE`` (1e-12) of each
  other count as equal, and within it of 0 as 0, where scipy would divide by the rounding.
  Fewer than two pairs: no interval, no test.
* **unpaired** (``welch``), for two runs whose splits differ (another seed, number of runs,
  dataset, places, protocol or share of unknown places): the difference of the means
  x̄_a − x̄_b, Welch's standard error √(s_a²/n_a + s_b²/n_b), its degrees of freedom
  (Welch–Satterthwaite: (s_a²/n_a + s_b²/n_b)² / ((s_a²/n_a)²/(n_a − 1) + (s_b²/n_b)²/(n_b − 1))),
  the interval x̄_a − x̄_b ± t₀.₉₇₅,df · SE, and Welch's t-test p
  (``scipy.stats.ttest_ind(equal_var=False)``). Such a difference is always marked
  **splits differ**. Either side with fewer than two values, or no spread on either side
  (SE = 0): no interval, no test.

Rates are in [0, 1] as in ``Evaluation``; a difference in the same unit. Pure functions of
the numbers: which sets are paired is the caller's decision (``compare.same_splits``).
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np
from scipy import stats

from vpr_explorer.errors import VPRInputError

#: Confidence of every interval.
LEVEL = 0.95
#: Differences (and spreads) within this of each other count as equal: float rounding of rates.
EQUAL_TOLERANCE = 1e-12


def _values(name: str, values: Sequence[float] | np.ndarray) -> np.ndarray:
    a = np.asarray(values, dtype=np.float64)
    if a.ndim != 1:
        raise VPRInputError(f"{name}: give one number per split (a 1-D sequence), not shape {a.shape}")
    return a


@contextmanager
def _exact() -> Iterator[None]:
    """scipy warns of "catastrophic cancellation" whenever a side holds one value repeated (a rate that is the
    same in every split of a run): that variance is exactly 0, not a rounding loss."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="Precision loss occurred in moment calculation",
                                category=RuntimeWarning)
        yield


def t_quantile(df: float) -> float:
    """t₀.₉₇₅ with ``df`` degrees of freedom (NaN for df ≤ 0 or NaN)."""
    return float(stats.t.ppf(0.5 + LEVEL / 2, df)) if np.isfinite(df) and df > 0 else math.nan


def _pct(x: float, scale: float, digits: int, sign: bool = False) -> str:
    if not np.isfinite(x):
        return "—"
    return format(scale * x, f"{'+' if sign else ''}.{digits}f")


def _p_text(p: float) -> str:
    return "p < 0.001" if p < 0.001 else f"p = {p:.3f}"


@dataclass(frozen=True)
class Summary:
    """mean ± std (ddof 1) of ``n`` values over splits and the 95% t interval of the mean (NaN where n < 2).

    ``note`` says what a lone number is when it is not one split's (``single``: a number
    pooled over the splits).
    """

    n: int
    mean: float
    std: float
    low: float
    high: float
    note: str = ""

    def text(self, scale: float = 1.0, digits: int = 3) -> str:
        """``"0.550 ± 0.041 [95% 0.499, 0.601]"``; one value: the value and ``(1 split)`` or its note; none: ``"—"``."""
        if self.n == 0 or not np.isfinite(self.mean):
            return "—"
        if self.n == 1:
            return f"{_pct(self.mean, scale, digits)} ({self.note or '1 split'})"
        return (f"{_pct(self.mean, scale, digits)} ± {_pct(self.std, scale, digits)} "
                f"[95% {_pct(self.low, scale, digits)}, {_pct(self.high, scale, digits)}]")

    def to_dict(self) -> dict:
        num = lambda x: float(x) if np.isfinite(x) else None  # noqa: E731
        return {"n": self.n, "mean": num(self.mean), "std": num(self.std), "ci95_low": num(self.low),
                "ci95_high": num(self.high), **({"note": self.note} if self.note else {})}


NO_SUMMARY = Summary(0, math.nan, math.nan, math.nan, math.nan)


def single(value: float, note: str) -> Summary:
    """One number that is not a split's (e.g. pooled over the splits): no spread, no interval, ``note`` says why."""
    return Summary(1, float(value), math.nan, math.nan, math.nan, note)


def summary(values: Sequence[float] | np.ndarray) -> Summary:
    """``Summary`` of the finite values (module doc); NaN values (undefined in a split) are left out."""
    a = _values("values", values)
    a = a[np.isfinite(a)]
    n = len(a)
    if n == 0:
        return NO_SUMMARY
    mean = float(a.mean())
    if n == 1:
        return Summary(1, mean, math.nan, math.nan, math.nan)
    std = float(a.std(ddof=1))
    if std <= EQUAL_TOLERANCE * max(1.0, abs(mean)):
        std = 0.0
    half = t_quantile(n - 1) * std / math.sqrt(n)
    return Summary(n, mean, std, mean - half, mean + half)


@dataclass(frozen=True)
class Difference:
    """a − b over splits: paired (the same splits) or Welch's (splits differ), with its interval and p-value.

    Attributes:
        paired: the per-split differences were taken (the same splits); else Welch's comparison.
        n: pairs (paired), or ``(n_a, n_b)`` values (Welch's).
        mean: d̄ (paired) or x̄_a − x̄_b (Welch's).
        std: s_d of the per-split differences (paired); NaN for Welch's.
        se: the standard error of ``mean``.
        df: degrees of freedom of the t distribution (n − 1, or Welch–Satterthwaite).
        low, high: the 95% interval of ``mean``.
        p: the two-sided p-value (NaN where there is no test: ``note`` says why).
        note: ``"paired over 10 splits"``, ``"identical on every split"``, ``"splits differ: Welch's t-test"`` …
        tag: the kind of comparison in a word or two (``"paired"``, ``"splits differ"`` …), for a table cell.
    """

    paired: bool
    n: int | tuple[int, int]
    mean: float
    std: float
    se: float
    df: float
    low: float
    high: float
    p: float
    note: str
    tag: str = ""

    @property
    def identical(self) -> bool:
        """Paired, and every split gave the same value to both."""
        return self.paired and self.note == IDENTICAL

    def text(self, scale: float = 1.0, digits: int = 3, *, short: bool = False) -> str:
        """``"+0.050 [95% +0.021, +0.079], p = 0.004 (paired over 10 splits)"``; ``short``: ``tag`` for the note."""
        why = self.tag if short and self.tag else self.note
        if not np.isfinite(self.mean):
            return f"— ({why})"
        head = _pct(self.mean, scale, digits, sign=True)
        if np.isfinite(self.low):
            head += f" [95% {_pct(self.low, scale, digits, True)}, {_pct(self.high, scale, digits, True)}]"
        if np.isfinite(self.p):
            head += f", {_p_text(self.p)}"
        return f"{head} ({why})"

    def to_dict(self) -> dict:
        num = lambda x: float(x) if np.isfinite(x) else None  # noqa: E731
        return {"paired": self.paired, "n": list(self.n) if isinstance(self.n, tuple) else self.n,
                "mean": num(self.mean), "std": num(self.std), "se": num(self.se), "df": num(self.df),
                "ci95_low": num(self.low), "ci95_high": num(self.high), "p": num(self.p), "note": self.note,
                "tag": self.tag}


IDENTICAL = "identical on every split"
SPLITS_DIFFER = "splits differ"


def paired(a: Sequence[float] | np.ndarray, b: Sequence[float] | np.ndarray) -> Difference:
    """a − b on the same splits: per-split differences, their mean, 95% t interval and paired t-test (module doc).

    Args:
        a, b: ``(n_splits,)`` one value per split, split i of ``a`` and of ``b`` the same split;
            a split where either is NaN is left out.
    Raises:
        VPRInputError: ``a`` and ``b`` of different lengths (not the same splits).
    """
    a, b = _values("a", a), _values("b", b)
    if a.shape != b.shape:
        raise VPRInputError(f"paired: {len(a)} and {len(b)} values are not the same splits; compare them "
                            "with welch()")
    ok = np.isfinite(a) & np.isfinite(b)
    d = a[ok] - b[ok]
    n = len(d)
    if n == 0:
        return Difference(True, 0, math.nan, math.nan, math.nan, math.nan, math.nan, math.nan, math.nan,
                          "no split with both values", "no value")
    mean = float(d.mean())
    if n == 1:
        return Difference(True, 1, mean, math.nan, math.nan, math.nan, math.nan, math.nan, math.nan,
                          "one split: no interval, no test", "one split")
    if float(np.ptp(d)) <= EQUAL_TOLERANCE:  # no spread beyond rounding
        if abs(mean) <= EQUAL_TOLERANCE:
            return Difference(True, n, 0.0, 0.0, 0.0, n - 1, 0.0, 0.0, math.nan, IDENTICAL, IDENTICAL)
        return Difference(True, n, mean, 0.0, 0.0, n - 1, mean, mean, 0.0,
                          f"the same difference on all {n} splits", "paired, no spread")
    std = float(d.std(ddof=1))
    se = std / math.sqrt(n)
    half = t_quantile(n - 1) * se
    with _exact():
        p = float(stats.ttest_rel(a[ok], b[ok]).pvalue)
    return Difference(True, n, mean, std, se, n - 1, mean - half, mean + half, p, f"paired over {n} splits",
                      "paired")


def welch(a: Sequence[float] | np.ndarray, b: Sequence[float] | np.ndarray) -> Difference:
    """x̄_a − x̄_b of two runs whose splits differ: Welch's interval and t-test, marked ``splits differ``.

    Args:
        a, b: the finite values per split of each (any lengths; NaN left out).
    """
    a, b = _values("a", a), _values("b", b)
    a, b = a[np.isfinite(a)], b[np.isfinite(b)]
    na, nb = len(a), len(b)
    if not na or not nb:
        return Difference(False, (na, nb), math.nan, math.nan, math.nan, math.nan, math.nan, math.nan, math.nan,
                          f"{SPLITS_DIFFER}; a side has no value", SPLITS_DIFFER)
    mean = float(a.mean() - b.mean())
    if na < 2 or nb < 2:
        return Difference(False, (na, nb), mean, math.nan, math.nan, math.nan, math.nan, math.nan, math.nan,
                          f"{SPLITS_DIFFER}; one split on a side: no interval, no test", SPLITS_DIFFER)
    va, vb = float(a.var(ddof=1)) / na, float(b.var(ddof=1)) / nb
    se = math.sqrt(va + vb)
    if se <= EQUAL_TOLERANCE:
        return Difference(False, (na, nb), mean, math.nan, 0.0, math.nan, math.nan, math.nan, math.nan,
                          f"{SPLITS_DIFFER}; no spread on either side: no test", SPLITS_DIFFER)
    df = (va + vb) ** 2 / (va**2 / (na - 1) + vb**2 / (nb - 1))
    half = t_quantile(df) * se
    with _exact():
        p = float(stats.ttest_ind(a, b, equal_var=False).pvalue)
    return Difference(False, (na, nb), mean, math.nan, se, df, mean - half, mean + half, p,
                      f"{SPLITS_DIFFER}: Welch's t-test, {na} and {nb} splits", SPLITS_DIFFER)

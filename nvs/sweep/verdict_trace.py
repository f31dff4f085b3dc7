"""What a verdict rests on, per test group: how many groups favour the paper's better row, an exact sign test, and
the fewest groups whose removal would undo the verdict (greedily, the ones that most favour the winner first)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from nvs.sweep.bootstrap import Gap, Paired, bootstrap, verdict

MAX_DROP = 3  # names shown; past that the verdict is said to survive dropping any 3 (greedily chosen) groups


def sign_test(wins: int, losses: int) -> float:
    """Exact two-sided binomial test of wins against losses at p = 1/2 (ties dropped before); 1.0 with none."""
    n = wins + losses
    if n == 0:
        return 1.0
    tail = sum(math.comb(n, i) for i in range(min(wins, losses) + 1)) / 2 ** n
    return min(1.0, 2 * tail)


@dataclass(frozen=True)
class Trace:
    """One ordering per test group: A's wins, losses and ties, the sign test, the groups that undo the verdict."""

    wins: int
    losses: int
    ties: int
    p_sign: float
    unit: str
    flips: tuple[str, ...] | None = None   # the groups dropped (see flip_set); None: an unresolved verdict
    survives: bool = False                 # dropping MAX_DROP groups left the verdict standing


def oriented(p: Paired, higher_is_better: bool) -> np.ndarray:
    """(G,) per-group Δ turned so that > 0 means row A is better."""
    d = p.group_deltas()
    return d if higher_is_better else -d


def flip_set(p: Paired, decided: str, higher_is_better: bool, max_drop: int = MAX_DROP) -> tuple[tuple[str, ...], bool]:
    """(groups dropped, survived): drop the group that most favours the winner, re-decide, until the verdict is no
    longer ``decided`` or ``max_drop`` groups are gone."""
    o = oriented(p, higher_is_better)
    order = np.argsort(-o if decided == "agree" else o, kind="stable")  # most in the winner's favour first
    dropped: list[int] = []
    for i in order[:max_drop]:
        dropped.append(int(i))
        if verdict(bootstrap(p.without(set(dropped))), higher_is_better) != decided:
            return tuple(p.names[j] for j in dropped), False
    return tuple(p.names[j] for j in dropped), True


def trace(p: Paired, gap: Gap, higher_is_better: bool) -> Trace:
    """The per-group account of one ordering (``gap`` is the bootstrap of ``p``)."""
    o = oriented(p, higher_is_better)
    wins, losses = int((o > 0).sum()), int((o < 0).sum())
    decided = verdict(gap, higher_is_better)
    flips, survives = flip_set(p, decided, higher_is_better) if decided != "unresolved" else (None, False)
    return Trace(wins, losses, len(o) - wins - losses, sign_test(wins, losses), p.unit, flips, survives)


def trace_text(t: Trace, a: str) -> str:
    """'a better on 12/15 models, sign test p = 0.035; undone without: x, y' (or '≥4' when 3 are not enough)."""
    n = t.wins + t.losses + t.ties
    text = f"{a} better on {t.wins}/{n} {t.unit}" + (f" ({t.ties} tied)" if t.ties else "")
    text += f", sign test p = {t.p_sign:.3g}"
    if t.flips is not None:
        text += "; undone without: " + (f"≥{MAX_DROP + 1} {t.unit}" if t.survives else ", ".join(t.flips))
    return text

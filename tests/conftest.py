"""Shared test helpers."""

from __future__ import annotations

import re
from collections.abc import Callable

import pytest

# A floating-point literal of USDA text (integers and the digits inside names are left to the
# text comparison). Kept independent of d3grasp.authoring.precision: this is the reference.
_FLOAT = re.compile(
    r"(?<![\w.])[-+]?(?:\d+\.\d*|\.\d+|\d+)(?:[eE][-+]?\d+)|(?<![\w.])[-+]?(?:\d+\.\d*|\.\d+)"
)


def usda_differences(a: str, b: str, *, rtol: float = 1e-6, atol: float = 1e-9, limit: int = 5) -> list[str]:
    """Where two USDA texts differ beyond round-off: text outside floats must match exactly,
    floats within ``atol + rtol * |b|``. Returns up to ``limit`` descriptions (empty: equal)."""
    lines_a, lines_b = a.splitlines(), b.splitlines()
    if len(lines_a) != len(lines_b):
        return [f"{len(lines_a)} lines against {len(lines_b)}"]
    out = []
    for n, (la, lb) in enumerate(zip(lines_a, lines_b, strict=True), start=1):
        if _FLOAT.sub("#", la) != _FLOAT.sub("#", lb):
            out.append(f"line {n}: {la.strip()[:120]!r} against {lb.strip()[:120]!r}")
        else:
            for x, y in zip(_FLOAT.findall(la), _FLOAT.findall(lb), strict=True):
                if abs(float(x) - float(y)) > atol + rtol * abs(float(y)):
                    out.append(f"line {n}: {x} against {y}")
                    break
        if len(out) >= limit:
            break
    return out


@pytest.fixture
def assert_usda_matches() -> Callable[[str, str], None]:
    """``assert_usda_matches(rebuilt_text, committed_text, hint)``: equal up to round-off."""

    def check(rebuilt: str, committed: str, hint: str = "") -> None:
        diffs = usda_differences(rebuilt, committed)
        assert not diffs, f"rebuilt file differs from the committed one ({hint}): " + "; ".join(diffs)

    return check

"""Numbers in authored files at a stated precision, so a rebuild gives the same bytes on any machine.

The authoring arithmetic (NumPy's SIMD sums and trigonometry, BLAS, trimesh's mass integrals)
differs between CPUs in the last one or two digits of a double: ``...75956546164`` here,
``...75956546165`` there. Written at full precision, that difference reaches the committed
files. So every floating-point number an authored USD layer or manifest holds is written

- with at most SIGNIFICANT_DIGITS (9) significant digits: every float32 value exactly (float32's
  shortest round-trip form has at most 9), doubles to 1e-9 relative, a nanometre on a metre;
- on a grid of RELATIVE_GRID (1e-12) times the largest magnitude of the tuple it belongs to
  (a position, a quaternion, an extent; a lone number is its own tuple). This catches numbers
  that come out of a cancellation, such as a quaternion component of -1.7e-8 from a rotation a
  hair off a right angle: their last digits move by ~1e-16 of the tuple's scale, a large
  *relative* change that significant digits alone would keep;
- as 0 below ZERO_BELOW (1e-15) in magnitude: round-off around an exact zero. The smallest
  physical number in the library, a pad's principal inertia, is ~2e-8 kg m^2.

All three are far above the ~1e-16 round-off and far below any physical tolerance.
"""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from typing import Any

SIGNIFICANT_DIGITS = 9
RELATIVE_GRID_DECIMALS = 12  # the grid is 10^-12 of the tuple's largest magnitude (to a power of 10)
ZERO_BELOW = 1e-15

# A number is not preceded or followed by a letter, digit, '_' or '.', so the digits of prim names
# such as hull_000 are never touched.
_NUMBER = r"(?<![\w.])[-+]?(?:\d+\.\d*|\.\d+|\d+)(?:[eE][-+]?\d+)?(?![\w.])"
_NUMBER_IN_TUPLE = re.compile(r"[-+]?(?:\d+\.\d*|\.\d+|\d+)(?:[eE][-+]?\d+)?")
# One USDA token that may hold numbers (a tuple of numbers, or one number), or a span whose text
# must stay as it is: string literals (triple-quoted first), asset paths @...@, comments (the
# "#usda 1.0" header among them) and Sdf paths <...>.
_USDA_TOKEN = re.compile(
    r'"""[\s\S]*?"""'
    r"|'''[\s\S]*?'''"
    r'|"(?:\\.|[^"\\\n])*"'
    r"|'(?:\\.|[^'\\\n])*'"
    r"|@[^@\n]*@"
    r"|#[^\n]*"
    r"|<[^>\n]*>"
    rf"|\(\s*{_NUMBER}(?:\s*,\s*{_NUMBER})*\s*\)"
    rf"|{_NUMBER}"
)


def stable_floats(values: Sequence[float]) -> list[float]:
    """One tuple's numbers at the stated precision (see the module docstring).

    Python's ``round`` and float formatting are correctly rounded on every platform, so equal
    inputs give equal outputs everywhere, and inputs a few ulps apart give equal outputs unless
    they straddle a rounding boundary (a chance of about 1e-4 per number). Negative zero is
    written as zero; NaN and infinities pass through.
    """
    xs = [float(v) for v in values]
    finite = [abs(x) for x in xs if math.isfinite(x) and abs(x) >= ZERO_BELOW]
    if not finite:
        return [x if not math.isfinite(x) else 0.0 for x in xs]
    exponent = int(f"{max(finite):e}".split("e")[1])  # from the formatted number: exact everywhere
    decimals = RELATIVE_GRID_DECIMALS - exponent
    out = []
    for x in xs:
        if not math.isfinite(x):
            out.append(x)
        elif abs(x) < ZERO_BELOW:
            out.append(0.0)
        else:
            out.append(float(f"{round(x, decimals):.{SIGNIFICANT_DIGITS}g}") + 0.0)  # + 0.0: no -0.0
    return out


def stable_float(x: float) -> float:
    """A lone number at the stated precision: ``stable_floats([x])[0]``."""
    return stable_floats([x])[0]


def stable_json(value: Any) -> Any:
    """A copy of a JSON-able value (dicts, lists, tuples, numbers) with every float made stable;
    a list of numbers is one tuple."""
    if isinstance(value, bool):
        return value
    if isinstance(value, float):
        return stable_float(value)
    if isinstance(value, dict):
        return {k: stable_json(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        if value and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value):
            if any(isinstance(v, float) for v in value):
                return [
                    r if isinstance(v, float) else v for v, r in zip(value, stable_floats(value), strict=True)
                ]
            return list(value)
        return [stable_json(v) for v in value]
    return value


def _number_text(tok: str, value: float) -> str:
    if not any(c in tok for c in ".eE"):
        return "0" if tok in ("-0", "+0") else tok  # integers; USD writes a float32 -0.0 as "-0"
    return repr(value)


def _stable_token(match: re.Match[str]) -> str:
    tok = match.group(0)
    if tok[0] in "\"'@#<":
        return tok  # text spans stay as written
    if tok[0] == "(":
        nums = _NUMBER_IN_TUPLE.findall(tok)
        stable = stable_floats([float(n) for n in nums])
        return "(" + ", ".join(_number_text(n, v) for n, v in zip(nums, stable, strict=True)) + ")"
    return _number_text(tok, stable_float(float(tok)))


def stable_usda_text(text: str) -> str:
    """USDA text with every floating-point literal made stable (strings, paths, comments untouched)."""
    return _USDA_TOKEN.sub(_stable_token, text)


def export_layer(layer: Any, path: str) -> None:
    """Write an ``Sdf.Layer`` to ``path`` (``.usda`` or ``.usdc``) with every float made stable.

    The layer's text is rounded, parsed back into an anonymous layer and exported from there,
    so the file (text or binary) holds exactly the rounded values, in USD's own formatting.
    """
    from pxr import Sdf

    stable = Sdf.Layer.CreateAnonymous(".usda")
    if not stable.ImportFromString(stable_usda_text(layer.ExportToString())):
        raise ValueError(f"{path}: the rounded layer did not parse back (a USDA token was misread)")
    if not stable.Export(str(path)):
        raise OSError(f"{path}: USD could not write the file")

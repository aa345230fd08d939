"""The analysis's options, their defaults and checks, and the error it reports bad input
with. Kept free of heavy imports so that ``bam-study --help`` stays fast."""

from __future__ import annotations

import math
from collections.abc import Iterable

DEFAULT_THRESHOLDS = (0.5, 0.8)
DEFAULT_FDR = 0.2
DEFAULT_BASELINE = "bam"


class InputError(Exception):
    """The study's data or an option is wrong; the message says where (file, row, column)."""


def check_thresholds(thresholds: Iterable[float]) -> tuple[float, ...]:
    """The thresholds in increasing order; each in (0, 1], none twice."""
    values = tuple(float(t) for t in thresholds)
    if not values:
        raise InputError("--thresholds: give at least one threshold")
    for value in values:
        if not (math.isfinite(value) and 0 < value <= 1):
            raise InputError(
                f"--thresholds: {value:g} is outside (0, 1]; thresholds are fractions of the "
                "optimal return, for example 0.5,0.8"
            )
    if len(set(values)) != len(values):
        raise InputError("--thresholds: a threshold is given twice")
    return tuple(sorted(values))


def parse_thresholds(text: str) -> tuple[float, ...]:
    """``"0.5,0.8"`` -> ``(0.5, 0.8)``."""
    parts = [part.strip() for part in text.split(",")]
    values = []
    for part in parts:
        try:
            values.append(float(part))
        except ValueError:
            raise InputError(
                f"--thresholds: {part!r} is not a number; give fractions separated by commas, "
                "for example 0.5,0.8"
            ) from None
    return check_thresholds(values)


def check_fdr(fdr: float) -> float:
    """A false discovery rate in (0, 1)."""
    fdr = float(fdr)
    if not (math.isfinite(fdr) and 0 < fdr < 1):
        raise InputError(f"--fdr: {fdr:g} is outside (0, 1); for example 0.2")
    return fdr


def parse_fdr(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise InputError(f"--fdr: {text!r} is not a number; for example 0.2") from None
    return check_fdr(value)


def parse_flags(text: str) -> tuple[str, ...]:
    """Quality checks (``quality.csv``'s flags), separated by commas, each once."""
    from server.app.export.quality import FLAGS

    names = tuple(dict.fromkeys(part.strip() for part in text.split(",")))
    unknown = [name for name in names if name not in FLAGS]
    if not names or unknown:
        raise InputError(
            f"--exclude-flagged: {', '.join(map(repr, unknown or [text]))} is not a quality "
            f"check; choose from {', '.join(FLAGS)}"
        )
    return names

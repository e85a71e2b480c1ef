"""Small value checks shared by the configurations and the public functions.

Counts and microseconds must be whole numbers: ``int(2.5)`` would silently become 2 and
``int("abc")`` fail deep inside a caller, so the checks refuse instead (and never take a bool,
which Python counts as an int).

>>> is_whole(3), is_whole(3.0), is_whole(2.5), is_whole(True), is_whole("3")
(True, True, False, False, False)
>>> is_int(3.0)
False
"""

from __future__ import annotations

import math

import numpy as np


def is_int(value) -> bool:
    """An integer (Python or numpy), not a bool."""
    return isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_))


def is_whole(value) -> bool:
    """An integer, or a float holding one (as YAML or arithmetic may give); not a bool."""
    if is_int(value):
        return True
    return isinstance(value, (float, np.floating)) and math.isfinite(value) and float(value).is_integer()

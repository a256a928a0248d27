"""Where two model descriptions differ: what a resumed fit keeps from its checkpoint.

A model description is the JSON-like dict a model's ``describe()`` returns and its checkpoint stores
(sizes, resolutions, bounds in world ENU metres, sampler settings). Comparing the checkpoint's with that of
a model freshly built from the options a resume was asked for names every property the options would
change, without a hand-kept list of which options shape the model.
"""

from __future__ import annotations

import math


def description_differences(saved, fresh, rel_tol: float = 1e-9) -> dict[str, tuple]:
    """``{dotted path: (saved value, fresh value)}`` for each leaf where ``saved`` and ``fresh`` differ.

    Dicts are compared key by key (a key only one side has is a difference, its missing value None). A
    list or tuple is one leaf, reported whole when any element differs (a list equals the same tuple);
    floats within ``rel_tol`` (relative) are equal, and an int equals the same float.
    """
    out: dict[str, tuple] = {}
    _walk(saved, fresh, "", out, rel_tol)
    return out


def _walk(a, b, path: str, out: dict, rel_tol: float) -> None:
    if isinstance(a, dict) and isinstance(b, dict):
        for k in sorted(set(a) | set(b), key=str):
            sub = f"{path}.{k}" if path else str(k)
            if k not in a or k not in b:
                out[sub] = (a.get(k), b.get(k))
            else:
                _walk(a[k], b[k], sub, out, rel_tol)
        return
    if isinstance(a, list | tuple) and isinstance(b, list | tuple):
        inner: dict[str, tuple] = {}
        if len(a) == len(b):
            for i, (x, y) in enumerate(zip(a, b, strict=True)):
                _walk(x, y, str(i), inner, rel_tol)
        if len(a) != len(b) or inner:
            out[path] = (a, b)
        return
    if not _same_leaf(a, b, rel_tol):
        out[path] = (a, b)


def _same_leaf(a, b, rel_tol: float) -> bool:
    numbers = (int, float)
    if isinstance(a, bool) or isinstance(b, bool):
        return a is b
    if isinstance(a, numbers) and isinstance(b, numbers):
        if math.isnan(a) or math.isnan(b):
            return math.isnan(a) and math.isnan(b)
        return math.isclose(a, b, rel_tol=rel_tol, abs_tol=0.0)
    return a == b

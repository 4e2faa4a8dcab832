"""Checks of what a command computed, made before it is written and success is claimed.

A command that writes geometry or images (``body export``, ``maps``, ``render``) passes what it is about
to write through these checks; each refuses with :class:`DegenerateOutputError` (a ValueError: one line,
exit 2) that names the input the output came from (``cause``, e.g. ``--motion far.npz frame 0``), so a
user learns which argument to change instead of finding a broken file after a "wrote ..." line:

:func:`check_finite`
    no NaN or infinity (a NaN pixel is written as black, a NaN vertex breaks every viewer).
:func:`check_points`
    point coordinates that float arithmetic can still tell apart: a body moved 1e20 m from the origin
    is stored in float32 as one point repeated (float32 keeps about 7 significant digits), and one
    moved 100 km away in steps of centimetres. Refused when the steps of the coordinates' dtype at
    their largest magnitude are coarser than ``detail`` (default: a thousandth of the points'
    extent, so a 1.7 m body may be moved about 10 km, not 20).
:func:`check_varies`
    not one value throughout where the content cannot be uniform (the normal map of a body).

Only numpy is needed; nothing of garmentnerf is imported.
"""

from __future__ import annotations

import numpy as np

__all__ = ["RELATIVE_DETAIL", "DegenerateOutputError", "check_finite", "check_points", "check_varies"]

#: The finest detail :func:`check_points` asks the coordinates to keep by default, as a fraction of
#: the points' extent.
RELATIVE_DETAIL = 1e-3


class DegenerateOutputError(ValueError):
    """What a command computed is not finite or has collapsed (one line naming its cause; exit 2)."""


def _array(values) -> np.ndarray:
    if hasattr(values, "detach"):  # a torch tensor, without importing torch
        values = values.detach().cpu().numpy()
    return np.asarray(values)


def check_finite(values, what: str, cause: str) -> None:
    """Refuse ``values`` (an array or tensor: ``what``, made from ``cause``) holding NaN or infinity."""
    array = _array(values)
    if array.dtype.kind not in "fc":
        return
    bad = ~np.isfinite(array)
    if bad.any():
        kinds = " and ".join(k for k, present in (("NaN", np.isnan(array).any()), ("infinity", np.isinf(array).any()))
                             if present)
        raise DegenerateOutputError(f"{cause}: {what} holds {int(bad.sum())} of {array.size} values that are "
                                    f"not finite ({kinds}); not written")


def check_points(points, what: str, cause: str, *, detail: float | None = None, dtype=None) -> None:
    """Refuse the points ``points`` ((N, D): ``what``, made from ``cause``) when they are not finite or when
    their coordinates cannot keep ``detail``: the distance between neighbouring values of ``dtype``
    (default: the points' own, float32 for integers) at the coordinates' largest magnitude is more than
    ``detail`` (default: :data:`RELATIVE_DETAIL` of the points' extent), or when they are all one point.
    """
    array = _array(points)
    check_finite(array, what, cause)
    if array.size == 0:
        return
    kind = np.dtype(dtype) if dtype is not None else (array.dtype if array.dtype.kind == "f" else np.dtype(np.float32))
    flat = array.reshape(-1, array.shape[-1]).astype(np.float64)
    extent = float((flat.max(axis=0) - flat.min(axis=0)).max())
    magnitude = float(np.abs(flat).max())
    step = float(np.spacing(kind.type(magnitude))) if magnitude > 0 else 0.0
    needed = RELATIVE_DETAIL * extent if detail is None else float(detail)
    if extent == 0.0 and len(flat) > 1:
        raise DegenerateOutputError(
            f"{cause}: {what} collapses to one point: its coordinates reach {magnitude:.3g}, where {kind.name} "
            f"holds values {step:.3g} apart; bring it nearer the origin; not written")
    if step > needed:
        raise DegenerateOutputError(
            f"{cause}: {what} loses its shape: its coordinates reach {magnitude:.3g}, where {kind.name} holds "
            f"values {step:.3g} apart, coarser than the {needed:.3g} it needs ({extent:.3g} across); bring it "
            f"nearer the origin; not written")


def check_varies(values, what: str, cause: str) -> None:
    """Refuse ``values`` (``what``, made from ``cause``) that hold one value throughout (after
    :func:`check_finite`), where the content cannot be uniform."""
    array = _array(values)
    check_finite(array, what, cause)
    if array.size > 1 and np.all(array == array.flat[0]):
        raise DegenerateOutputError(f"{cause}: {what} is {array.flat[0]:.6g} throughout (degenerate); not written")

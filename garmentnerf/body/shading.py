"""Polynomial shading of a unit normal: the basis of the body's learned irradiance ``S(n)``.

On the unit sphere the monomials ``x^a y^b z^c`` with ``a + b + c <= d`` span exactly the real
spherical harmonics of degree <= d, so a linear combination of them is SH lighting of that order
written without any SH constants. :mod:`garmentnerf.model.body_appearance` evaluates it in torch
and :mod:`garmentnerf.gl.body_layer_pass` writes the same sum out in GLSL, both from
:func:`monomial_exponents`, so the two cannot disagree on the order of the terms.
"""

from __future__ import annotations

import itertools

import torch


def monomial_exponents(degree: int) -> list[tuple[int, int, int]]:
    """Exponents ``(a, b, c)`` of every monomial ``x^a y^b z^c`` with ``a + b + c <= degree``,
    constant first, then by total degree (``(degree + 1)(degree + 2)(degree + 3) / 6`` of them)."""
    if degree < 0:
        raise ValueError(f"degree must be >= 0, got {degree}")
    out = [e for e in itertools.product(range(degree + 1), repeat=3) if sum(e) <= degree]
    return sorted(out, key=lambda e: (sum(e), tuple(-x for x in e)))


def normal_monomials(normals: torch.Tensor, degree: int) -> torch.Tensor:
    """(N, 3) unit normals -> (N, K) the monomials of :func:`monomial_exponents` at each normal."""
    powers = [torch.ones_like(normals)]
    for _ in range(degree):
        powers.append(powers[-1] * normals)
    cols = [powers[a][:, 0] * powers[b][:, 1] * powers[c][:, 2] for a, b, c in monomial_exponents(degree)]
    return torch.stack(cols, dim=-1)


__all__ = ["monomial_exponents", "normal_monomials"]

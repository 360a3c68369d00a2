"""The turntable encoder's angle error as the fits see it: once and twice per turn.

A code disc mounted off-centre reads the platter's angle with an error once per turn, and a disc
that is not quite round adds a second harmonic (DESIGN §9, the encoder): the angle a return is
given is φ + e(φ), with

    e(φ) = a₁·sin φ + b₁·cos φ + a₂·sin 2φ + b₂·cos 2φ.

Neither fixture's fit models e: each takes the angles as they are read, and moves its estimate
of H by what e does to its residuals. Both fixtures turn on the same encoder, so they move
together, by different amounts: each fit says how its estimate follows each coefficient (per
radian of it, :data:`HARMONICS`), and the combination (:mod:`calstation.engine.fusion`) carries
the coefficients as parameters of their own, held by the encoder's stated accuracy, so that the
σ covers what the encoder may do and the two fixtures' disagreement is judged with it.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import numpy as np

from calstation.engine.frames import FloatArray

HARMONICS = ("encoder_sin1", "encoder_cos1", "encoder_sin2", "encoder_cos2")
"""The encoder error's coefficients a₁, b₁, a₂, b₂ (rad), in the order of :func:`basis`."""

STEP = 1e-4
"""Central-difference step (rad) of a fit's residuals by a coefficient: their response is linear
in e over far more than an encoder's error."""


def basis(cos: FloatArray, sin: FloatArray) -> FloatArray:
    """(N, 4) sin φ, cos φ, sin 2φ, cos 2φ of the angles whose cosines and sines are given (the
    fits keep them, not the angles): e(φ) is basis times the coefficients."""
    return np.column_stack([sin, cos, 2.0 * sin * cos, cos * cos - sin * sin])


def turned(cos: FloatArray, sin: FloatArray, step: float) -> tuple[FloatArray, FloatArray]:
    """The cosines and sines of the angles turned by ``step`` (rad): cos(φ + h), sin(φ + h)."""
    c, s = math.cos(step), math.sin(step)
    return cos * c - sin * s, sin * c + cos * s


def columns(directions: Mapping[str, Mapping[str, float]] | None, names: Sequence[str],
            sigma: float) -> FloatArray:
    """(n, 4) how an estimate of the parameters ``names`` moves per 1σ (``sigma``, rad) of each
    coefficient, from how it follows each per radian (``directions``, by :data:`HARMONICS`;
    missing: it does not)."""
    given = directions or {}
    return np.array([[float(given.get(h, {}).get(n, 0.0)) * sigma for h in HARMONICS]
                     for n in names])


def coefficient_sigma(accuracy: float) -> float:
    """1σ (rad) of each coefficient of an encoder whose stated accuracy is ``accuracy`` (rad, the
    largest error of its reading over a turn): accuracy/√2, so that a single harmonic of that
    amplitude, at any phase, lies at √2 σ of its two coefficients together."""
    return accuracy / math.sqrt(2.0)

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

import numpy as np

from calstation.engine.frames import FloatArray

HARMONICS = ("encoder_sin1", "encoder_cos1", "encoder_sin2", "encoder_cos2")
"""The encoder error's coefficients a₁, b₁, a₂, b₂ (rad), in the order of :func:`basis`."""

STEP = 1e-4
"""Central-difference step (rad) of a fit's residuals by a coefficient: their response is linear
in e over far more than an encoder's error."""


def basis(phi: FloatArray) -> FloatArray:
    """(N, 4) sin φ, cos φ, sin 2φ, cos 2φ of the angles ``phi`` (rad): e(φ) is basis times
    the coefficients."""
    return np.column_stack([np.sin(phi), np.cos(phi), np.sin(2.0 * phi), np.cos(2.0 * phi)])


def coefficient_sigma(accuracy: float) -> float:
    """1σ (rad) of each coefficient of an encoder whose stated accuracy is ``accuracy`` (rad, the
    largest error of its reading over a turn): accuracy/√2, so that a single harmonic of that
    amplitude, at any phase, lies at √2 σ of its two coefficients together."""
    return accuracy / math.sqrt(2.0)

"""The attitude LQR's Riccati solution (structure-preserving doubling, in C++) against SciPy's
solve_discrete_are (a generalised Schur method) on the same A, B, Q, R, as kinfly-flight-lqr
prints them: two independent algorithms agreeing on P and K."""
from __future__ import annotations

import json
import subprocess

import numpy as np
import scipy.linalg

from conftest import built

# Both solvers are backward stable; P's entries span ten orders of magnitude and the closed loop
# has poles near 1 at 1 kHz, which costs SciPy some digits: they agree to ~1e-12, measured.
RELATIVE_TOLERANCE = 1e-6


def lqr_design() -> dict[str, np.ndarray]:
    printed = subprocess.run([built("bin/kinfly-flight-lqr")], check=True, capture_output=True,
                             text=True).stdout
    return {key: np.array(value) for key, value in json.loads(printed).items()}


def relative_error(ours: np.ndarray, theirs: np.ndarray) -> float:
    """Largest entry-wise difference against the largest entry of the same row: entries that are
    exactly zero in one (decoupled axes) are judged at the scale of their row."""
    scale = np.abs(theirs).max(axis=1, keepdims=True)
    return float((np.abs(ours - theirs) / scale).max())


def test_riccati_solution_and_gain_match_scipy() -> None:
    design = lqr_design()
    A, B, Q, R = design["A"], design["B"], design["Q"], design["R"]
    assert A.shape == (9, 9) and B.shape == (9, 3)
    P = scipy.linalg.solve_discrete_are(A, B, Q, R)
    K = np.linalg.solve(R + B.T @ P @ B, B.T @ P @ A)
    assert relative_error(design["P"], P) < RELATIVE_TOLERANCE
    assert relative_error(design["K"], K) < RELATIVE_TOLERANCE


def test_closed_loop_is_stable() -> None:
    design = lqr_design()
    poles = np.linalg.eigvals(design["A"] - design["B"] @ design["K"])
    assert np.abs(poles).max() < 1.0
    assert np.isclose(np.abs(poles).max(), float(design["closed_loop_spectral_radius"]))

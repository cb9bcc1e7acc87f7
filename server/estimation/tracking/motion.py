"""The PDR step model shared by the trackers.

A step of length d along heading h (degrees clockwise from +y) moves the position by
f(d, h) = (d·sin h, d·cos h). With d and h uncertain (step.length_std_m,
step.heading_std_deg), the first-order covariance of the displacement is
J·diag(σd², σh²)·Jᵀ with J = ∂f/∂(d, h) (h in radians).
"""

from __future__ import annotations

import math

import numpy as np

from server.estimation.types import Step, step_displacement

__all__ = ["step_displacement", "step_jacobian", "step_noise_cov", "step_input_cov"]


def step_jacobian(length_m: float, heading_deg: float) -> np.ndarray:
    """∂(dx, dy)/∂(d, h) with h in radians: [[sin h, d·cos h], [cos h, −d·sin h]]."""
    h = math.radians(heading_deg)
    s, c = math.sin(h), math.cos(h)
    return np.array([[s, length_m * c], [c, -length_m * s]])


def step_input_cov(step: Step) -> np.ndarray:
    """diag(σd², σh²) with σh in radians."""
    return np.diag([step.length_std_m**2, math.radians(step.heading_std_deg) ** 2])


def step_noise_cov(step: Step) -> np.ndarray:
    """First-order covariance of one step's displacement, J·diag(σd², σh²)·Jᵀ (m²)."""
    J = step_jacobian(step.length_m, step.heading_deg)
    return J @ step_input_cov(step) @ J.T

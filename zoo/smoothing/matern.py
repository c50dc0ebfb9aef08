"""The Matern-5/2 GP as a linear SDE, in closed form: numpy for inference, torch for gradients.

The Matern-5/2 GP is the first component of the state (f, f', f'') of the SDE ds = F s dt + L dW with F's
characteristic polynomial (x + lam)^3, lam = sqrt(5) / lengthscale. Since F + lam I is nilpotent,
exp(F dt) = exp(-lam dt) (I + N dt + N^2 dt^2 / 2) in closed form, and the process noise of a step is
Q = P - A P A^T for the stationary covariance P. Every state-space smoother of the package (the GP's
``statespace`` backend, the robust smoother, the online smoother) builds its prior from these forms; the
torch twin :func:`matern52_model_torch` lets the robust smoother's M-step differentiate through them.
"""

from __future__ import annotations

import math

import numpy as np
import torch

#: the identity of the state (read only: every use makes a new array from it)
_EYE3 = np.eye(3)


def matern52_nilpotent(lengthscale: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """lam = sqrt(5) / lengthscale (B,), the nilpotent N = F + lam I (B, 3, 3) of the SDE and N^2."""
    lam = np.sqrt(5.0) / lengthscale
    nil = np.zeros((lam.shape[0], 3, 3))
    nil[:, 0, 0] = nil[:, 1, 1] = lam
    nil[:, 0, 1] = nil[:, 1, 2] = 1.0
    nil[:, 2, 0], nil[:, 2, 1], nil[:, 2, 2] = -(lam**3), -3.0 * lam**2, -2.0 * lam
    return lam, nil, nil @ nil


def matern52_transition(dt: np.ndarray, lam: np.ndarray, nil: np.ndarray, nil2: np.ndarray) -> np.ndarray:
    """exp(F dt) = exp(-lam dt) (I + N dt + N^2 dt^2 / 2) per step and axis, (n, B, 3, 3)."""
    d = dt[:, None, None, None]
    return np.exp(-lam[None, :, None, None] * d) * (_EYE3 + nil * d + nil2 * (d * d / 2.0))


def matern52_model(
    dt: np.ndarray, lengthscale: np.ndarray, outputscale: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Transition matrices A (n, B, 3, 3), process noises Q and stationary covariance P (B, 3, 3).

    ``dt`` (n,) are the steps in seconds; ``lengthscale`` and ``outputscale`` (B,) one value per axis.
    """
    lam, nil, nil2 = matern52_nilpotent(lengthscale)
    stationary = np.zeros((lam.shape[0], 3, 3))
    stationary[:, 0, 0] = 1.0
    stationary[:, 1, 1] = lam**2 / 3.0
    stationary[:, 0, 2] = stationary[:, 2, 0] = -(lam**2) / 3.0
    stationary[:, 2, 2] = lam**4
    stationary *= outputscale[:, None, None]
    A = matern52_transition(dt, lam, nil, nil2)
    Q = stationary - A @ stationary @ np.swapaxes(A, -1, -2)
    return A, Q, stationary


def matern52_model_torch(
    dt: torch.Tensor, lengthscale: torch.Tensor, outputscale: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Differentiable twin of :func:`matern52_model`: A, Q (N, B, 3, 3) and P (B, 3, 3)."""
    lam = math.sqrt(5.0) / lengthscale  # (B,)
    B = lam.shape[0]
    zero, one = torch.zeros_like(lam), torch.ones_like(lam)
    nil = torch.stack([
        torch.stack([lam, one, zero], -1),
        torch.stack([zero, lam, one], -1),
        torch.stack([-(lam**3), -3.0 * lam**2, -2.0 * lam], -1),
    ], -2)  # F + lam I
    stationary = torch.stack([
        torch.stack([one, zero, -(lam**2) / 3.0], -1),
        torch.stack([zero, lam**2 / 3.0, zero], -1),
        torch.stack([-(lam**2) / 3.0, zero, lam**4], -1),
    ], -2) * outputscale[:, None, None]
    d = dt[:, None, None, None]
    eye = torch.eye(3, dtype=dt.dtype).expand(B, 3, 3)
    A = torch.exp(-lam[None, :, None, None] * d) * (eye + nil * d + (nil @ nil) * (d * d / 2.0))
    Q = stationary - A @ stationary @ A.transpose(-1, -2)
    return A, 0.5 * (Q + Q.transpose(-1, -2)), stationary

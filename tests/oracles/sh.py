"""Real spherical harmonics from scipy's complex ones: the oracle of the SH basis
(``splat/sh.py``) and of the colours a PLY export stores."""

import numpy as np
import scipy.special as sp


def scipy_real_sh(dirs: np.ndarray, degree: int) -> np.ndarray:
    """[N, (degree+1)^2] real SH, index l^2 + l + m: sqrt(2) Re / Im of scipy's complex
    Y_l^|m| (Condon-Shortley phase included) for m > 0 / m < 0, Y_l^0 for m = 0."""
    d = dirs / np.linalg.norm(dirs, axis=-1, keepdims=True)
    theta, phi = np.arccos(np.clip(d[:, 2], -1, 1)), np.arctan2(d[:, 1], d[:, 0])
    cols = []
    for l in range(degree + 1):  # noqa: E741  the degree l of Y_l^m
        for m in range(-l, l + 1):
            y = sp.sph_harm_y(l, abs(m), theta, phi)
            cols.append(np.sqrt(2) * y.imag if m < 0 else np.sqrt(2) * y.real if m > 0 else y.real)
    return np.stack(cols, -1)

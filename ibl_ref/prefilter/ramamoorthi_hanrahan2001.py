"""Ramamoorthi & Hanrahan (2001), "An Efficient Representation for Irradiance Environment Maps" — SH9 irradiance.

SIGGRAPH 2001, Sec. 2–3.  The irradiance ``E(n) = ∫ L(ω) max(n·ω, 0) dω`` of a Lambertian surface is the spherical
convolution of L with the clamped cosine ``A(c) = max(c, 0)``, whose Legendre coefficients decay fast; keeping the
bands l ≤ 2 (9 coefficients) gives (equation numbers of the paper as we know them)::

    L_lm = ∫ L(ω) Y_lm(ω) dω                                 (Eq. 3; here Σ_j L_j Y_lm(ω_j) Ω_j over every texel,
                                                              exact texel solid angles Ω_j)
    E(n) ≈ Σ_{l≤2} Σ_m Â_l L_lm Y_lm(n),   Â_0 = π, Â_1 = 2π/3, Â_2 = π/4       (Eq. 7–9)

with the real SH in Cartesian form (Eq. 10; exact constants, the paper prints them to 6 digits):
``Y_00 = 1/(2√π)``; ``(Y_1−1, Y_10, Y_11) = √(3/(4π))·(y, z, x)``; ``(Y_2−2, Y_2−1, Y_21) = ½√(15/π)·(xy, yz, xz)``;
``Y_20 = ¼√(5/π)(3z² − 1)``; ``Y_22 = ¼√(15/π)(x² − y²)``.  Expanded, E is a quadratic polynomial in the normal
(Eq. 13):

    E(n) = c1 L22 (x² − y²) + c3 L20 z² + c4 L00 − c5 L20
           + 2 c1 (L2−2 xy + L21 xz + L2−1 yz) + 2 c2 (L11 x + L1−1 y + L10 z)

``c1 = Â_2·¼√(15/π) = √(15π)/16 ≈ 0.429043``, ``c2 = Â_1·√(3/(4π))/2 = √(π/3)/2 ≈ 0.511664``,
``c3 = 3Â_2·¼√(5/π) = 3√(5π)/16 ≈ 0.743125``, ``c4 = Â_0/(2√π) = √π/2 ≈ 0.886227``,
``c5 = Â_2·¼√(5/π) = √(5π)/16 ≈ 0.247708`` (the paper's printed values).  The Lambertian radiance is
``Lo = kd·E(n)/π``.

Error (derived here, rigorous)
------------------------------
By the addition theorem ``Σ_m Y_lm(a) Y_lm(b) = (2l+1)/(4π) P_l(a·b)``, the discrete SH9 irradiance is exactly
``E9(n) = Σ_j L_j A9(n·ω_j) Ω_j`` with the truncated kernel ``A9(c) = Σ_{l≤2} Â_l (2l+1)/(4π) P_l(c) =
3/32 + c/2 + 15c²/32``, while the exact cosine convolution over the same texels
(:func:`ibl_ref.groundtruth.kan2015.irradiance_map`, times π) is ``Σ_j L_j max(n·ω_j, 0) Ω_j``.  Since
``max_c |A9(c) − max(c, 0)| = 3/32`` (at the terminator c = 0; |·| = 0.0396 at c = ±8/15 and 1/16 at c = ±1), for
L ≥ 0

    |E9(n) − E(n)| ≤ (3/32) · Σ_j L_j Ω_j       (:func:`error_bound`; per channel, in irradiance units)

and a single directional light attains it: SH9 then over-estimates the irradiance at the terminator by 3/32 ≈ 9.4 %
of the peak irradiance, over-estimates the peak by 1/16, and is *negative* (−19/480 of the peak) at 122° from the
light.  For a map that contains only bands 0–2 the continuum E9 is exact (the truncation only removes the l ≥ 3
part of A, orthogonal to L); discretely up to the O(N⁻²) error of the texel quadrature
(``tests/test_ramamoorthi_hanrahan2001.py``).  The paper reports average errors of about 1 % and at most ≈ 9 % in
theory for typical maps.
"""

from __future__ import annotations

import numpy as np

from ..environment import envmap
from ..errors import IBLError, LayoutError
from ..groundtruth.convolution_args import check_cube
from .interface import check_lobe_param

__all__ = ["A_HAT", "SH9_CONSTANTS", "C1", "C2", "C3", "C4", "C5", "KERNEL_ERROR_MAX", "sh9_basis",
           "sh9_coefficients", "irradiance", "irradiance_quadratic", "irradiance_cube", "lambertian_radiance",
           "error_bound", "SH9Irradiance"]

#: clamped-cosine band factors Â_0, Â_1, Â_2 (Eq. 8)
A_HAT = (np.pi, 2.0 * np.pi / 3.0, np.pi / 4.0)
_K0 = 0.5 / np.sqrt(np.pi)
_K1 = np.sqrt(3.0 / (4.0 * np.pi))
_K2 = 0.5 * np.sqrt(15.0 / np.pi)
_K20 = 0.25 * np.sqrt(5.0 / np.pi)
_K22 = 0.25 * np.sqrt(15.0 / np.pi)
#: the Cartesian SH constants of Eq. 10 (the paper prints 0.282095, 0.488603, 1.092548, 0.315392, 0.546274)
SH9_CONSTANTS = (_K0, _K1, _K2, _K20, _K22)
#: Eq. 13 constants (the paper prints 0.429043, 0.511664, 0.743125, 0.886227, 0.247708)
C1 = A_HAT[2] * _K22
C2 = 0.5 * A_HAT[1] * _K1
C3 = 3.0 * A_HAT[2] * _K20
C4 = A_HAT[0] * _K0
C5 = A_HAT[2] * _K20
#: max_c |A9(c) − max(c, 0)| = 3/32: the kernel error of the SH9 irradiance (module doc)
KERNEL_ERROR_MAX = 3.0 / 32.0


def sh9_basis(dirs) -> np.ndarray:
    """``Y_lm`` of Eq. 10 at unit directions (..., 3) → (..., 9), order l² + l + m: L00, L1−1, L10, L11, L2−2,
    L2−1, L20, L21, L22."""
    d = np.asarray(dirs, dtype=np.float64)
    x, y, z = d[..., 0], d[..., 1], d[..., 2]
    return np.stack([np.full(x.shape, _K0), _K1 * y, _K1 * z, _K1 * x, _K2 * x * y, _K2 * y * z,
                     _K20 * (3.0 * z * z - 1.0), _K2 * x * z, _K22 * (x * x - y * y)], axis=-1)


def sh9_coefficients(cube) -> np.ndarray:
    """``L_lm = Σ_j L_j Y_lm(ω_j) Ω_j`` over every texel (texel centres, exact solid angles): (9, C) float64."""
    a, _ = check_cube(cube)
    n = a.shape[1]
    Y = sh9_basis(envmap.texel_directions(n)).reshape(-1, 9)
    w = a.reshape(-1, a.shape[-1]) * envmap.cube_solid_angles(n).reshape(-1, 1)
    return Y.T @ w


def _check_coeffs(coeffs) -> np.ndarray:
    c = np.asarray(coeffs, dtype=np.float64)
    if c.ndim == 1:
        c = c[:, None]
    if c.ndim != 2 or c.shape[0] != 9:
        raise LayoutError(f"SH9 coefficients must have shape (9,) or (9, C), got {np.shape(coeffs)}")
    if not np.all(np.isfinite(c)):
        raise IBLError("SH9 coefficients contain NaN/Inf")
    return c


def irradiance(coeffs, normals) -> np.ndarray:
    """``E(n) = Σ Â_l L_lm Y_lm(n)`` (Eq. 7) at unit normals (..., 3) → (..., C)."""
    c = _check_coeffs(coeffs)
    n = envmap.unit_directions(normals, "normals")
    band = np.repeat(np.asarray(A_HAT), [1, 3, 5])
    return sh9_basis(n) @ (band[:, None] * c)


def irradiance_quadratic(coeffs, normals) -> np.ndarray:
    """The same E(n) from the quadratic polynomial of Eq. 13 (constants c1…c5) → (..., C)."""
    c = _check_coeffs(coeffs)
    n = envmap.unit_directions(normals, "normals")
    x, y, z = (n[..., i:i + 1] for i in range(3))
    L00, L1m1, L10, L11, L2m2, L2m1, L20, L21, L22 = c
    return (C1 * L22 * (x * x - y * y) + C3 * L20 * z * z + C4 * L00 - C5 * L20
            + 2.0 * C1 * (L2m2 * x * y + L21 * x * z + L2m1 * y * z) + 2.0 * C2 * (L11 * x + L1m1 * y + L10 * z))


def irradiance_cube(coeffs, out_size: int) -> np.ndarray:
    """E at the texel centres of a cube of face size ``out_size``: (6, M, M, C)."""
    try:
        m = envmap.check_face_size(out_size)
    except ValueError:
        raise IBLError(f"out_size must be a positive integer, got {out_size!r}") from None
    return irradiance(coeffs, envmap.texel_directions(m))


def lambertian_radiance(coeffs, normals, kd=1.0) -> np.ndarray:
    """Lambertian outgoing radiance ``kd·E(n)/π`` (..., C); ``kd`` ≥ 0 (scalar or per channel)."""
    kd = np.asarray(kd, dtype=np.float64)
    if not np.all(np.isfinite(kd)) or np.any(kd < 0):
        raise IBLError(f"kd must be finite and >= 0, got {kd!r}")
    return kd * irradiance(coeffs, normals) / np.pi


def error_bound(cube) -> np.ndarray:
    """Rigorous bound on ``|E9(n) − E(n)|`` for every normal n against the exact cosine convolution over the same
    texels: ``(3/32)·Σ_j L_j Ω_j`` per channel (C,) (module doc)."""
    a, _ = check_cube(cube)
    n = a.shape[1]
    return KERNEL_ERROR_MAX * np.einsum("fijc,fij->c", a, envmap.cube_solid_angles(n))


class SH9Irradiance:
    """Ramamoorthi & Hanrahan 2001 SH9 irradiance: 9 coefficients per channel, E(n) as a quadratic in n."""

    lobe = "cosine"
    paper = "Ramamoorthi & Hanrahan 2001, An Efficient Representation for Irradiance Environment Maps, Eq. 7-13"

    def __init__(self, cube):
        self._init(sh9_coefficients(cube), error_bound(cube))

    def _init(self, coeffs, error_bound_irradiance):
        self.coeffs = _check_coeffs(coeffs)
        self._bound = np.asarray(error_bound_irradiance, dtype=np.float64).reshape(-1)

    @classmethod
    def from_coefficients(cls, coeffs, error_bound_irradiance) -> "SH9Irradiance":
        """The method of given coefficients (9, C) and irradiance bound per channel (C,)."""
        obj = cls.__new__(cls)
        obj._init(coeffs, error_bound_irradiance)
        return obj

    @classmethod
    def build(cls, cube) -> "SH9Irradiance":
        return cls(cube)

    @property
    def nbytes(self) -> int:
        return int(self.coeffs.nbytes)

    @property
    def channel_bounds(self) -> np.ndarray:
        """(C,) bound of ``|lookup − E/π|`` per channel: (3/32)·Σ_j L_j Ω_j / π (module doc)."""
        return self._bound / np.pi

    @property
    def error_bound(self) -> float:
        """The largest channel bound (radiance units): ``|lookup(n) − E(n)/π| ≤ error_bound`` for every n, with
        E the exact cosine convolution over the same texels (the target of the ``"cosine"`` lobe family)."""
        return float(np.max(self.channel_bounds))

    def lookup(self, directions, param=1.0) -> np.ndarray:
        """``E(n)/π`` (..., C) at ``directions`` (normalised here); ``param`` is the cosine lobe's exponent, 1
        (``None`` allowed), checked by :func:`ibl_ref.prefilter.interface.check_lobe_param`."""

        out = irradiance(self.coeffs, directions) / np.pi  # normalises and checks the directions
        check_lobe_param(self.lobe, param, np.broadcast_to(np.zeros(3), out.shape[:-1] + (3,)))
        return out

    def shade(self, normals, kd=1.0) -> np.ndarray:
        return lambertian_radiance(self.coeffs, normals, kd)

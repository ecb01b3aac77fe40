"""Tests of ibl_ref.rendering.vsm: Chebyshev bound, Ω → blur mapping, VSM vs ray-cast visibility, fp16 precision loss."""

import numpy as np
import pytest
import trimesh
from scipy.special import erf

from ibl_ref.rendering import raycast, vsm
from ibl_ref.errors import IBLError


def _quad(x0, x1, z0, z1, y):
    """Horizontal quad at height y, normal +y."""
    return trimesh.Trimesh([[x0, y, z0], [x1, y, z0], [x1, y, z1], [x0, y, z1]], [[0, 2, 1], [0, 3, 2]], process=False)


def _plane_and_box():
    box = trimesh.creation.box(extents=[1, 1, 1])
    box.apply_translation([0, 1.0, 0])  # spans y ∈ [0.5, 1.5]
    return [(_quad(-2, 2, -2, 2, 0.0), 0), (box, 1)]


def _fib_cap(n, axis, theta):
    """n directions evenly spread (Fibonacci spiral, equal solid angle) over the cap of half-angle theta."""
    k = np.arange(n) + 0.5
    ct = 1 - k / n * (1 - np.cos(theta))
    st = np.sqrt(1 - ct**2)
    phi = k * np.pi * (3 - np.sqrt(5))
    a = np.cross(axis, [1.0, 0, 0]) if abs(axis[0]) < 0.9 else np.cross(axis, [0, 1.0, 0])
    a /= np.linalg.norm(a)
    b = np.cross(axis, a)
    return ct[:, None] * axis + st[:, None] * (np.cos(phi)[:, None] * a + np.sin(phi)[:, None] * b)


def test_cap_half_angle():
    assert vsm.cap_half_angle(2 * np.pi) == pytest.approx(np.pi / 2, abs=1e-15)
    assert vsm.cap_half_angle(4 * np.pi) == pytest.approx(np.pi, abs=1e-15)
    # small-angle limit θ ≈ √(Ω/π) (docs/background.md §4); series Ω = πθ²(1 − θ²/12 + …) → rel. diff θ²/24 ≈ 1.3e-5
    om = 1e-3
    assert vsm.cap_half_angle(om) == pytest.approx(np.sqrt(om / np.pi), rel=1e-4)


def test_chebyshev_closed_form_and_bound():
    # hand value: μ = 0.5, E[x²] = 0.26 → σ² = 0.01; t = 0.6 → 0.01 / (0.01 + 0.01) = 0.5
    assert vsm.chebyshev_upper_bound(0.6, 0.5, 0.26, 1e-9) == pytest.approx(0.5, rel=1e-12)
    assert vsm.chebyshev_upper_bound(0.4, 0.5, 0.26, 1e-9) == 1.0  # receiver in front of the mean
    # one-sided Chebyshev (Cantelli) inequality: P(X ≥ t) ≤ p_max for any distribution, t > μ
    rng = np.random.default_rng(11)
    for _ in range(50):
        x = rng.choice(rng.uniform(0, 1, 3), size=200) + rng.normal(0, 0.01, 200)
        m1, m2 = x.mean(), (x * x).mean()
        for t in np.linspace(m1 + 1e-3, x.max(), 5):
            assert np.mean(x >= t) <= vsm.chebyshev_upper_bound(t, m1, m2, 1e-12) + 1e-12


def test_light_bleeding_reduction():
    p = np.array([0.0, 0.2, 0.6, 1.0])
    np.testing.assert_allclose(vsm.reduce_light_bleeding(p, 0.2), [0, 0, 0.5, 1.0], atol=1e-15)
    np.testing.assert_array_equal(vsm.reduce_light_bleeding(p, 0.0), p)


def test_plane_under_box_umbra_lit_penumbra():
    scene = _plane_and_box()
    L = np.array([0.2, 1.0, 0.1])
    L /= np.linalg.norm(L)
    sm = vsm.build_vsm(scene, L, 0.1, resolution=256, occluder_distance=0.5)
    assert sm.sigma_texels > 1
    # shadow of the box bottom centre (0, 0.5, 0) on y = 0 is at −0.5·(Lx, Lz)/Ly
    c = -0.5 * np.array([L[0], 0, L[2]]) / L[1]
    umbra = vsm.visibility(c[None], sm)
    lit = vsm.visibility(np.array([[1.8, 0, 1.8], [-1.8, 0, -1.8], [1.8, 0, -1.5]]), sm)
    assert umbra[0] < 1e-3  # Chebyshev bound with σ²_min = 1e-6 leaves ~1e-5 in a full umbra
    np.testing.assert_array_equal(lit, 1.0)  # receiver at the mean depth → p = 1 exactly (t ≤ μ branch)
    # along a line from the umbra centre outward (+x) visibility never decreases
    xs = np.linspace(c[0], 1.8, 200)
    line = np.c_[xs, np.zeros_like(xs), np.full_like(xs, c[2])]
    v = vsm.visibility(line, sm)
    assert v[0] < 1e-3 and v[-1] == 1.0
    # tolerance: in the umbra p_max ≈ σ²/(t−μ)² ~ 5e-5 and float32 cancellation in M2 − M1² (~3e-8 absolute on a
    # variance of ~1e-6) makes it fluctuate by a few 1e-6
    assert np.all(np.diff(v) >= -1e-5)
    # hard-shadow limit (σ = 0) equals exact ray-cast visibility except within 2 texels of the shadow edge
    hard = vsm.build_vsm(scene, L, 0.0, resolution=256, sigma_texels=0.0)
    ex = raycast.directional_visibility(scene, line, np.tile([0, 1.0, 0], (len(line), 1)), L)
    edge_x = xs[np.argmax(ex > 0.5)]
    far_from_edge = np.abs(xs - edge_x) > 2 * hard.camera.texel_size
    # 0.01: Chebyshev is only an upper bound; where bilinear filtering mixes two blocker depths (box top and side
    # faces) it leaks ~0.005 into the umbra (the light-bleeding artefact of VSM)
    np.testing.assert_allclose(vsm.visibility(line, hard)[far_from_edge], ex[far_from_edge], atol=0.01)


def test_penumbra_width_follows_solid_angle():
    # A plate with a straight edge at x = 0, height Δd = 0.5, over a receiver, light overhead with cap half-angle
    # θ = 0.3.  Exact visibility (ray cast, 600 equal-solid-angle directions) is the CDF of the disc's 1D marginal
    # (radius ρ = Δd·tanθ); the VSM of a single-depth blocker is exactly 1 − (Gaussian-blurred coverage), i.e. a
    # Gaussian CDF with σ = ρ/2 under the module's mapping.  Their difference is bounded by the closed-form
    # difference of the two CDFs plus 0.03 (edge rasterized to ±½ texel, bilinear look-up, 600-direction quadrature).
    scene = [(_quad(-1, 1, -1, 1, 0.0), 0), (_quad(-1.2, 0.0, -1, 1, 0.5), 1)]
    L = np.array([0.0, 1.0, 0.0])
    theta = 0.3
    omega = 2 * np.pi * (1 - np.cos(theta))
    xs = np.linspace(-0.4, 0.4, 41)
    pts = np.c_[xs, np.zeros_like(xs), np.zeros_like(xs)]
    exact = raycast.visibility_to_directions(scene, pts, None, _fib_cap(600, L, theta)).mean(axis=1)
    rho = 0.5 * np.tan(theta)
    u = np.clip(xs / rho, -1, 1)
    semicircle_cdf = 0.5 + (u * np.sqrt(1 - u * u) + np.arcsin(u)) / np.pi
    gauss_cdf = 0.5 * (1 + erf(xs / (rho / 2 * np.sqrt(2))))
    assert np.abs(exact - semicircle_cdf).max() < 0.02  # the ray-cast reference is what theory says
    tol = np.abs(gauss_cdf - semicircle_cdf).max() + 0.03
    sm = vsm.build_vsm(scene, L, omega, resolution=512, occluder_distance=0.5)
    v = vsm.visibility(pts, sm)
    assert np.abs(v - gauss_cdf).max() < 0.03
    assert np.abs(v - exact).max() < tol
    # the test discriminates: a blur twice as wide misses the tolerance
    wide = vsm.build_vsm(scene, L, omega, resolution=512, sigma_texels=2 * sm.sigma_texels)
    assert np.abs(vsm.visibility(pts, wide) - exact).max() > tol


def test_float16_loses_precision():
    # Same scene, same parameters; float64 VSM is the precision reference.  RG16F (the paper's format) stores
    # M2 with spacing 2⁻¹³ near 0.25, so the variance M2 − M1² of a lit, flat receiver (true value ~0) is
    # dominated by rounding; float32 keeps it ~1e-8.
    scene = _plane_and_box()
    L = np.array([0.3, 1.0, -0.2])
    L /= np.linalg.norm(L)
    rng = np.random.default_rng(4)
    pts = np.c_[rng.uniform(-1.9, 1.9, 3000), np.zeros(3000), rng.uniform(-1.9, 1.9, 3000)]
    maps = {dt: vsm.build_vsm(scene, L, 0.02, resolution=256, occluder_distance=0.5, dtype=dt)
            for dt in ("float64", "float32", "float16")}
    vis = {dt: vsm.visibility(pts, m) for dt, m in maps.items()}
    err32 = np.abs(vis["float32"] - vis["float64"]).max()
    err16 = np.abs(vis["float16"] - vis["float64"]).max()
    assert err32 < 1e-3
    assert err16 > 10 * err32
    var = {dt: m.moments[..., 1].astype(float) - m.moments[..., 0].astype(float) ** 2 for dt, m in maps.items()}
    assert np.abs(var["float16"] - var["float64"]).max() > 100 * np.abs(var["float32"] - var["float64"]).max()
    assert maps["float16"].moments.dtype == np.float16


def test_bad_vsm_inputs():
    scene = _plane_and_box()
    with pytest.raises(IBLError, match="dtype"):
        vsm.build_vsm(scene, [0, 1, 0], 0.01, dtype="bfloat16")
    with pytest.raises(IBLError, match="solid angle"):
        vsm.build_vsm(scene, [0, 1, 0], -0.1)
    with pytest.raises(IBLError, match="bleeding"):
        vsm.build_vsm(scene, [0, 1, 0], 0.01, bleed_reduction=1.0)
    sm = vsm.build_vsm(scene, [0, 1, 0], 0.01, resolution=32)
    with pytest.raises(IBLError, match="NaN"):
        vsm.visibility([[np.nan, 0, 0]], sm)

"""Tests of ibl_ref.groundtruth.kan2015 (Kán et al. 2015, Eq. 2-4): irradiance and specular maps."""

import numpy as np
import pytest

from ibl_ref.environment import envmap
from ibl_ref.errors import IBLError
from ibl_ref.groundtruth.kan2015 import irradiance_map, phong_brdf, reflected_radiance, specular_map, specular_maps
from ibl_ref.groundtruth.phong_convolution import convolve_exact


def test_constant_env_gives_constant_maps():
    # Ed = (1/π) ∫ c max(cos,0) dω = c·π/π = c ;  Es^n = (n+1)/(2π) · c · 2π/(n+1) = c.
    # "literal" quadrature carries the discretisation error of Σ cos^n Ω vs 2π/(n+1): observed at
    # N=16 ≤ 1.6e-4 (n=1), 2.6e-3 (n=16) (see test_phong_convolution) → tolerance 5e-3.
    c = 0.8
    cube = np.full((6, 16, 16, 3), c)
    np.testing.assert_allclose(irradiance_map(cube), c, rtol=5e-4)
    np.testing.assert_allclose(specular_maps(cube, [4.0, 16.0]), c, rtol=5e-3)
    # "normalized" quadrature: the lobe average, exactly c to rounding
    np.testing.assert_allclose(irradiance_map(cube, quadrature="normalized"), c, rtol=1e-14)
    np.testing.assert_allclose(specular_map(cube, 60.0, quadrature="normalized"), c, rtol=1e-14)


def test_irradiance_of_gradient_is_closed_form():
    # L = a + b·ω: (1/π)∫(a + b·ω) max(n·ω,0) dω = a + b·n (2π/3)/π = a + (2/3) b·n.  Quadrature
    # error at N=16 observed ~5e-5 (s=1 row of the convergence experiment) → tolerance 5e-4.
    n = 16
    d = envmap.texel_directions(n)
    b = np.array([0.2, 0.5, -0.1])
    cube = (1.0 + d @ b)[..., None]
    ed = irradiance_map(cube)[..., 0]
    np.testing.assert_allclose(ed, 1.0 + (2.0 / 3.0) * (d @ b), atol=5e-4)


def test_maps_relate_to_phong_convolution():
    rng = np.random.default_rng(11)
    cube = rng.random((6, 6, 6, 3))
    # Ed is the s = 1 lobe average (normalised quadrature) and (1/π)·unnormalised (literal)
    np.testing.assert_allclose(irradiance_map(cube, quadrature="normalized"), convolve_exact(cube, 1.0), rtol=1e-13)
    np.testing.assert_allclose(irradiance_map(cube), convolve_exact(cube, 1.0, normalized=False) / np.pi, rtol=1e-13)
    es = specular_map(cube, 10.0)
    np.testing.assert_allclose(es, convolve_exact(cube, 10.0, normalized=False) * 11.0 / (2 * np.pi), rtol=1e-13)


def test_brute_force_eq3_sum():
    # Kán Eq. 3 evaluated by brute force in the test with exact solid angles in place of 2π/N:
    # Lo = Σ [kd/π + ks (n+1)/(2π) cos^n α / |n·ωi|] L_i |n·ωi| Ω_i over the normal's hemisphere.
    # With ωr = n the specular lobe's hemisphere is the normal's hemisphere, so the map's lobe-hemisphere
    # integral and the BRDF integral cover the same texels; they must agree to rounding.
    rng = np.random.default_rng(2)
    N = 5
    cube = rng.random((6, N, N, 1))
    d = envmap.texel_directions(N).reshape(-1, 3)
    om = envmap.cube_solid_angles(N).reshape(-1)
    L = cube.reshape(-1)
    j = 37  # an output texel: normal = ωr = its direction
    nrm = d[j]
    kd, ks, shin = 0.3, 0.6, 8.0
    cos_n = d @ nrm
    cos_a = d @ nrm  # ωr = n (view along the normal)
    hemi = cos_n > 0
    f = phong_brdf(kd, ks, shin, cos_a[hemi], cos_n[hemi])
    lo_brute = np.sum(f * L[hemi] * cos_n[hemi] * om[hemi])
    ed = irradiance_map(cube).reshape(-1)[j]
    es = specular_map(cube, shin).reshape(-1)[j]
    assert reflected_radiance(ed, es, kd, ks) == pytest.approx(lo_brute, rel=1e-12)


def test_phong_brdf_energy_and_errors():
    # energy of the specular term: ∫ ks (n+1)/(2π) cos^n α / cosθ · cosθ dω = ks when the lobe is
    # centred on the normal; by quadrature in μ
    from scipy.integrate import quad

    n = 12.0
    e = quad(lambda mu: 2 * np.pi * phong_brdf(0.0, 1.0, n, mu, mu) * mu, 0, 1)[0]
    assert e == pytest.approx(1.0, rel=1e-8)  # quad default epsrel 1.5e-8
    with pytest.raises(IBLError, match=r"phong_brdf: \|n·ωi\| = 0 where the"):
        phong_brdf(0.5, 0.5, 4.0, 1.0, 0.0)
    with pytest.raises(IBLError, match=r"quadrature must be one of \('literal'"):
        irradiance_map(np.ones((6, 2, 2, 3)), quadrature="exact")
    with pytest.raises(IBLError, match=r"Phong exponent s must be >="):
        specular_maps(np.ones((6, 2, 2, 3)), [0.5])

"""Tests of the occlusion methods (ibl_ref.occlusion): the exact and smoothstep spherical-cap intersections, each
method's formula at its limits and at hand-computed points, shade(), PRT against numerically integrated transfer
vectors, the input checks and the registry."""

import dataclasses
import math

import numpy as np
import pytest
from scipy.integrate import quad

from ibl_ref.errors import IBLError
from ibl_ref.groundtruth.sh_basis import real_sh
from ibl_ref.occlusion import OCCLUSION_METHODS, OcclusionInputs, OcclusionMethod, OcclusionResult, UnoccludedTerms
from ibl_ref.occlusion import get, shade
from ibl_ref.occlusion.interface import INPUT_FIELDS
from ibl_ref.occlusion.spherical_caps import cap_intersection_exact, cap_intersection_smoothstep

TWO_PI = 2.0 * np.pi


def _unit(x):
    x = np.asarray(x, dtype=np.float64)
    return x / np.linalg.norm(x, axis=-1, keepdims=True)


def _inputs(P=1, n=(0.0, 0.0, 1.0), v=(0.0, 0.0, 1.0), roughness=0.5, **fields):
    n = np.broadcast_to(_unit(n), (P, 3)).copy()
    v = np.broadcast_to(_unit(v), (P, 3)).copy()
    return OcclusionInputs(normal=n, view=v, roughness=roughness, **fields)


def _small_cap(c1, c2):
    return TWO_PI * (1.0 - np.maximum(c1, c2))


# ----------------------------------------------------------------------------------------------
# exact intersection of two caps
# ----------------------------------------------------------------------------------------------
#: (θ1, θ2, d): partial overlaps small and large, caps beyond a hemisphere, containment, disjoint, covering
CAP_CASES = [
    (0.5, 0.4, 0.6), (0.3, 0.3, 0.1), (1.0, 0.2, 1.0), (np.pi / 2, np.pi / 2, 1.0), (2.0, 0.5, 2.2),
    (2.0, 1.8, 2.5), (2.6, 2.6, np.pi), (2.6, 1.0, 0.5), (1.2, 0.3, 0.5), (0.4, 0.5, 1.2), (0.2, 2.9, 3.0),
    (2.2, 1.4, 1.7), (0.9, 0.9, 1.79), (3.0, 3.0, 0.7),
]


@pytest.fixture(scope="module")
def sphere_mc():
    """10⁶ uniform directions on the sphere (seeded): their z and x components."""
    rng = np.random.default_rng(20240611)
    w = rng.normal(size=(1_000_000, 3))
    w /= np.linalg.norm(w, axis=1, keepdims=True)
    return w[:, 2].copy(), w[:, 0].copy()


def test_exact_cap_intersection_matches_monte_carlo(sphere_mc):
    wz, wx = sphere_mc
    N = wz.size
    for t1, t2, d in CAP_CASES:
        in1 = wz >= math.cos(t1)                                    # axis a1 = z
        in2 = math.sin(d) * wx + math.cos(d) * wz >= math.cos(t2)  # axis a2 = (sin d, 0, cos d)
        p = np.count_nonzero(in1 & in2) / N
        exact = float(cap_intersection_exact(math.cos(t1), math.cos(t2), math.cos(d)))
        q = exact / (4 * np.pi)
        sigma = 4 * np.pi * math.sqrt(max(q * (1 - q), 1e-12) / N)
        assert abs(4 * np.pi * p - exact) <= 5 * sigma, (t1, t2, d, 4 * np.pi * p, exact)


def _quadrature_intersection(t1, t2, d):
    """Ω(C1 ∩ C2) as ∫ over the polar angle θ about a2 (0..θ2) of sin θ times the azimuth of that circle inside C1:
    an independent derivation, by adaptive quadrature."""
    def arc(th):
        den = math.sin(th) * math.sin(d)
        num = math.cos(t1) - math.cos(th) * math.cos(d)
        if den <= 0.0:
            return TWO_PI if num <= 0 else 0.0
        x = num / den
        return TWO_PI if x <= -1 else 0.0 if x >= 1 else 2 * math.acos(x)

    breaks = sorted(b for b in (abs(t1 - d), t1 + d, TWO_PI - t1 - d) if 0 < b < t2)
    edges = [0.0, *breaks, t2]
    return sum(quad(lambda th: math.sin(th) * arc(th), a, b, epsabs=1e-13, epsrel=1e-12, limit=200)[0]
               for a, b in zip(edges[:-1], edges[1:]))


def test_exact_cap_intersection_matches_quadrature():
    rng = np.random.default_rng(7)
    cases = CAP_CASES + [tuple(x) for x in rng.uniform(0.05, np.pi - 0.05, size=(20, 3))]
    for t1, t2, d in cases:
        exact = float(cap_intersection_exact(math.cos(t1), math.cos(t2), math.cos(d)))
        assert exact == pytest.approx(_quadrature_intersection(t1, t2, d), abs=1e-9), (t1, t2, d)


def test_exact_cap_intersection_closed_forms():
    t = np.linspace(0.0, np.pi, 37)
    c = np.cos(t)
    # d = 0: the smaller cap; identical caps: the cap itself
    C1, C2 = np.meshgrid(c, c, indexing="ij")
    assert np.allclose(cap_intersection_exact(C1, C2, 1.0), TWO_PI * (1 - np.maximum(C1, C2)), rtol=0, atol=1e-13)
    assert np.allclose(cap_intersection_exact(c, c, 1.0), TWO_PI * (1 - c), rtol=0, atol=1e-13)
    # two hemispheres with axes d apart: a lune of 2(π − d)
    d = np.linspace(0.0, np.pi, 61)
    assert np.allclose(cap_intersection_exact(0.0, 0.0, np.cos(d)), 2 * (np.pi - d), rtol=0, atol=1e-12)
    # the whole sphere (θ = π) leaves the other cap; a point cap (θ = 0) has no area
    dd = np.cos(np.linspace(0, np.pi, 13))
    assert np.allclose(cap_intersection_exact(-1.0, 0.3, dd), TWO_PI * 0.7, rtol=0, atol=1e-13)
    assert np.all(cap_intersection_exact(1.0, 0.3, dd) == 0.0)
    # antipodal axes: disjoint (θ1 + θ2 ≤ π) or the band Ω1 + Ω2 − 4π
    assert cap_intersection_exact(np.cos(1.0), np.cos(2.0), -1.0) == pytest.approx(0.0, abs=1e-15)
    assert cap_intersection_exact(np.cos(2.5), np.cos(2.0), -1.0) == pytest.approx(
        -TWO_PI * (np.cos(2.5) + np.cos(2.0)), abs=1e-13)


def test_exact_cap_intersection_identities():
    """Symmetry, and C1 ∩ C2 + C1 ∩ complement(C2) = C1 (the complement is a cap about −a2 of half-angle π − θ2)."""
    rng = np.random.default_rng(3)
    c1, c2, cd = rng.uniform(-1, 1, size=(3, 20000))
    a = cap_intersection_exact(c1, c2, cd)
    assert np.allclose(a, cap_intersection_exact(c2, c1, cd), rtol=0, atol=1e-13)
    assert np.allclose(a + cap_intersection_exact(c1, -c2, -cd), TWO_PI * (1 - c1), rtol=0, atol=2e-13)
    assert np.all((a >= 0) & (a <= _small_cap(c1, c2)))


def test_exact_cap_intersection_near_case_boundaries_is_continuous():
    """Tangent (inside and outside), covering and antipodal configurations, approached from both sides."""
    for t1, t2 in [(0.7, 0.4), (2.0, 1.5), (2.5, 2.9), (1.0, 1.0), (np.pi / 2, 0.3)]:
        small = _small_cap(np.cos(t1), np.cos(t2))
        for d0, limit in [(abs(t1 - t2), small), (t1 + t2, 0.0),
                          (TWO_PI - t1 - t2, -TWO_PI * (np.cos(t1) + np.cos(t2)))]:
            if not 0.0 <= d0 <= np.pi:
                continue
            for eps in (-1e-9, 0.0, 1e-9):
                d = min(max(d0 + eps, 0.0), np.pi)
                val = float(cap_intersection_exact(np.cos(t1), np.cos(t2), np.cos(d)))
                assert np.isfinite(val) and 0.0 <= val <= small
                assert val == pytest.approx(limit, abs=1e-6), (t1, t2, d0, eps)


def test_exact_cap_intersection_tiny_cap_keeps_relative_accuracy():
    """A cap of 1e-6 rad centred on the boundary of a 1 rad cap: about half of it inside (the boundary's geodesic
    curvature cot(1) moves the fraction by O(1e-6)); the arccos of the cosine rule would lose it entirely."""
    ts = 1e-6
    for tv in (0.5, 1.0, 2.0):
        frac = cap_intersection_exact(np.cos(tv), np.cos(ts), np.cos(tv)) / (TWO_PI * (1 - np.cos(ts)))
        assert frac == pytest.approx(0.5, abs=1e-5)


def test_cap_intersection_shapes_and_input_checks():
    out = cap_intersection_exact(np.zeros((2, 1)), np.zeros(3), 0.5)
    assert out.shape == (2, 3)
    assert isinstance(cap_intersection_exact(0.0, 0.0, 0.0), np.floating)
    assert float(cap_intersection_exact(1.0 + 1e-13, 0.0, 0.0)) == 0.0
    with pytest.raises(IBLError, match="cos1"):
        cap_intersection_exact(1.1, 0.0, 0.0)
    with pytest.raises(IBLError, match="cos_d"):
        cap_intersection_smoothstep(0.0, 0.0, np.nan)
    with pytest.raises(IBLError, match="broadcast"):
        cap_intersection_exact(np.zeros(2), np.zeros(3), 0.0)


# ----------------------------------------------------------------------------------------------
# smoothstep approximation
# ----------------------------------------------------------------------------------------------
def _cap_grid(tmax, n):
    t = np.linspace(0.0, tmax, n)[1:]
    d = np.linspace(0.0, np.pi, 2 * n)
    return np.meshgrid(np.cos(t), np.cos(t), np.cos(d), indexing="ij")


def test_smoothstep_equals_exact_in_containment_and_disjoint_cases():
    c1, c2, cd = _cap_grid(np.pi, 41)
    t1, t2, d = np.arccos(c1), np.arccos(c2), np.arccos(cd)
    ex, sm = cap_intersection_exact(c1, c2, cd), cap_intersection_smoothstep(c1, c2, cd)
    inside = d < np.abs(t1 - t2) - 1e-9
    apart = d > t1 + t2 + 1e-9
    assert inside.sum() > 100 and apart.sum() > 100
    assert np.array_equal(sm[inside], ex[inside]) and np.array_equal(sm[inside], _small_cap(c1, c2)[inside])
    assert np.all(sm[apart] == 0.0) and np.all(ex[apart] == 0.0)


def test_smoothstep_gap_to_exact_within_measured_bound():
    """Caps up to a hemisphere (every GTSO cone): |smoothstep − exact| ≤ 0.161 of the smaller cap's solid angle
    (measured max 0.1604 on a 161² × 322 grid, at two equal caps of 0.069 rad, d = 0.039); two hemispheres
    at d = π/3: 20/27 of 2π against 2(π − π/3)."""
    c1, c2, cd = _cap_grid(np.pi / 2, 61)
    gap = np.abs(cap_intersection_smoothstep(c1, c2, cd) - cap_intersection_exact(c1, c2, cd)) / _small_cap(c1, c2)
    assert 0.1 < gap.max() <= 0.161
    assert float(cap_intersection_smoothstep(0.0, 0.0, 0.5)) == pytest.approx(TWO_PI * 20 / 27, rel=1e-12)


# ----------------------------------------------------------------------------------------------
# the formulas at their limits and at hand-computed points
# ----------------------------------------------------------------------------------------------
def test_none_and_plain_ao():
    inp = _inputs(P=3, ao=np.array([0.0, 0.4, 1.0]))
    none = get("none")(inp)
    assert np.array_equal(none.diffuse_factor, np.ones(3)) and np.array_equal(none.specular_factor, np.ones(3))
    r = get("ao-diffuse")(inp)
    assert np.array_equal(r.diffuse_factor, inp.ao) and np.array_equal(r.specular_factor, np.ones(3))
    r = get("ao-both")(inp)
    assert np.array_equal(r.diffuse_factor, inp.ao) and np.array_equal(r.specular_factor, inp.ao)


@pytest.mark.parametrize("name", ["lagarde2014-alpha", "lagarde2014-r", "unreal-so"])
def test_specular_occlusion_from_ao_limits(name):
    nv = np.linspace(0.0, 1.0, 11)
    n = np.tile([0.0, 0.0, 1.0], (11, 1))
    v = np.stack([np.sqrt(1 - nv**2), np.zeros(11), nv], axis=1)
    for r in (0.0, 0.3, 1.0):
        one = get(name)(OcclusionInputs(normal=n, view=v, roughness=r, ao=np.ones(11)))
        zero = get(name)(OcclusionInputs(normal=n, view=v, roughness=r, ao=np.zeros(11)))
        assert np.all(one.specular_factor == 1.0) and np.all(one.diffuse_factor == 1.0)
        assert np.all(zero.specular_factor == 0.0) and np.all(zero.diffuse_factor == 0.0)


def test_specular_occlusion_from_ao_values():
    # n·v = 0.8, ao = 0.5, r = 0.5 (α = 0.25)
    inp = _inputs(v=(0.6, 0.0, 0.8), roughness=0.5, ao=np.array([0.5]))
    expected = {"lagarde2014-alpha": 1.3 ** 2.0 ** (-16 * 0.25 - 1) - 0.5,
                "lagarde2014-r": 1.3 ** 2.0 ** (-16 * 0.5 - 1) - 0.5,
                "unreal-so": 1.3 ** 0.25 - 0.5}
    for name, value in expected.items():
        assert get(name)(inp).specular_factor[0] == pytest.approx(value, rel=1e-14)
    # n·v < 0 (a normal-mapped normal facing away) is clamped to 0, never NaN
    back = get("lagarde2014-alpha")(_inputs(v=(0.6, 0.0, -0.8), ao=np.array([0.3])))
    assert back.specular_factor[0] == pytest.approx(max(0.3 ** 2.0 ** (-5) - 0.7, 0.0))
    # x = r of one label is x = α of the other at roughness √r
    a = get("lagarde2014-r")(_inputs(v=(0.6, 0, 0.8), roughness=0.36, ao=np.array([0.2])))
    b = get("lagarde2014-alpha")(_inputs(v=(0.6, 0, 0.8), roughness=0.6, ao=np.array([0.2])))
    assert a.specular_factor[0] == pytest.approx(b.specular_factor[0], rel=1e-14)


def test_multibounce_ao():
    V = np.linspace(0.0, 1.0, 21)
    rho = np.array([0.0, 0.5, 0.8, 1.0])
    res = get("multibounce-ao")(_inputs(P=21, ao=V, albedo=rho))
    assert res.diffuse_factor.shape == (21, 4) and np.all(res.specular_factor == 1.0)
    # ρ = 0: max(V, ((−0.3324 V + 0.6417) V + 0.6903) V)
    assert np.allclose(res.diffuse_factor[:, 0], np.maximum(V, ((-0.3324 * V + 0.6417) * V + 0.6903) * V),
                       rtol=0, atol=1e-15)
    # V = 1: a + b + c = 0.9996 + 0.0005 ρ (the fit overshoots 1 by 1e-4 at ρ = 1)
    assert np.allclose(res.diffuse_factor[-1], np.maximum(1.0, 0.9996 + 0.0005 * rho), rtol=0, atol=1e-14)
    assert res.diffuse_factor[-1, -1] == pytest.approx(1.0001, abs=1e-14)
    # V = 0 stays 0; brighter occluders give more light back
    assert np.all(res.diffuse_factor[0] == 0.0)
    assert np.all(np.diff(res.diffuse_factor[1:-1], axis=1) > 0)
    # a per-pixel albedo (P, C)
    per_pixel = get("multibounce-ao")(_inputs(P=2, ao=np.array([0.5, 0.5]), albedo=np.array([[0.0], [0.8]])))
    assert per_pixel.diffuse_factor[:, 0] == pytest.approx([0.5, ((1.29992 * 0.5 - 3.19438) * 0.5 + 2.89446) * 0.5],
                                                                rel=1e-14)


def _frame_for_reflection(R, n):
    """A view v with reflect(−v, n) = R (reflection is an involution: v = 2(n·R) n − R)."""
    R, n = _unit(R), _unit(n)
    return 2 * np.dot(n, R) * n - R


@pytest.mark.parametrize("name,k", [("horizon-k1.1", 1.1), ("horizon-k1.3", 1.3)])
def test_horizon_occlusion(name, k):
    n = _unit([0.5, 0.0, 1.0])
    ng = np.array([0.0, 0.0, 1.0])
    for cos_rg, h in [(-1.0 / k, 0.0), (-0.5 / k, 0.5), (0.0, 1.0), (0.4, 1.0), (-0.95, 0.0)]:
        R = np.array([math.sqrt(1 - cos_rg**2), 0.0, cos_rg])
        v = _frame_for_reflection(R, n)
        res = get(name)(_inputs(n=n, v=v, geo_normal=ng[None], ao=np.array([0.7])))
        assert res.specular_factor[0] == pytest.approx(h * h, abs=1e-12)
        assert res.diffuse_factor[0] == 0.7


def test_godot_horizon():
    # a view in front of the shading normal: R·n = n·v ≥ 0, nothing occluded
    res = get("godot-horizon")(_inputs(P=1, v=(0.6, 0.0, 0.8), roughness=0.0, ao=np.array([0.5])))
    assert res.specular_factor[0] == 1.0 and res.diffuse_factor[0] == 0.5
    # n·v = −0.8: R·n = −0.8, h = 0.2 at r = 0; r = 1 bends R onto n (h = 1); r² = 1/2: R' = normalize((R + n)/2)
    v = (0.6, 0.0, -0.8)
    R = np.array([-0.6, 0.0, -0.8])
    z = np.array([0.0, 0.0, 1.0])
    for r, cos_rn in [(0.0, -0.8), (1.0, 1.0), (math.sqrt(0.5), _unit(R + z)[2]), (0.6, _unit(R + 0.36 * (z - R))[2])]:
        h = min(1.0 + cos_rn, 1.0)
        res = get("godot-horizon")(_inputs(v=v, roughness=r, ao=np.array([1.0])))
        assert res.specular_factor[0] == pytest.approx(h * h, abs=1e-14), r
    # v = −n at r² = 1/2: R + r²(n − R) = 0, h taken as 1
    res = get("godot-horizon")(_inputs(v=(0.0, 0.0, -1.0), roughness=math.sqrt(0.5), ao=np.array([1.0])))
    assert res.specular_factor[0] == 1.0


GTSO = ["gtso-smoothstep-alpha", "gtso-smoothstep-r", "gtso-exact-alpha", "gtso-exact-r", "filament-gtso"]


@pytest.mark.parametrize("name", GTSO)
def test_gtso_limits(name):
    v = _unit([0.3, -0.2, 0.9])
    R = _frame_for_reflection(v, [0.0, 0.0, 1.0])  # reflect(−v, z) (the involution again)
    for r in (0.0, 0.05, 0.4, 1.0):
        # bent normal along R and everything visible: the whole specular cone is visible
        res = get(name)(_inputs(v=v, roughness=r, ao=np.array([1.0]), bent_normal=R[None]))
        assert res.specular_factor[0] == 1.0 and res.diffuse_factor[0] == 1.0
    # nothing visible: SO = 0 (a point visibility cone), unless Filament's fade lifts near-mirror lobes
    res = get(name)(_inputs(v=v, roughness=0.8, ao=np.array([0.0]), bent_normal=R[None]))
    assert res.specular_factor[0] == 0.0
    # a hemisphere of visibility (ao = 1) with its axis ⟂ R: the specular cone is cut in half by a great circle,
    # for the exact and (by the symmetry of its smoothstep about the midpoint) the smoothstep intersection
    side = _unit(np.cross(R, [1.0, 0.0, 0.0]))
    res = get(name)(_inputs(v=v, roughness=0.7, ao=np.array([1.0]), bent_normal=side[None]))
    assert res.specular_factor[0] == pytest.approx(0.5, abs=1e-12)
    # a mirror (r = 0): the indicator of R inside the visibility cone
    cos_v = math.sqrt(1 - 0.36)
    tilted = [_unit(np.cross(R, [1, 0, 0])) * math.sin(a) + R * math.cos(a) for a in (0.5, 0.8)]
    res = get(name)(_inputs(P=2, v=v, roughness=0.0, ao=np.full(2, 0.36), bent_normal=np.array(tilted)))
    expected = [1.0, 1.0] if name == "filament-gtso" else [float(math.cos(0.5) >= cos_v), float(math.cos(0.8) >= cos_v)]
    assert list(res.specular_factor) == expected


def test_gtso_roughness_inputs_and_value():
    v = _unit([0.2, 0.1, 0.95])
    R = _frame_for_reflection(v, [0.0, 0.0, 1.0])
    b = _unit(R + [0.4, 0.0, 0.0])[None]
    ao = np.array([0.55])
    for inter in ("smoothstep", "exact"):
        a = get(f"gtso-{inter}-r")(_inputs(v=v, roughness=0.36, ao=ao, bent_normal=b)).specular_factor
        b2 = get(f"gtso-{inter}-alpha")(_inputs(v=v, roughness=0.6, ao=ao, bent_normal=b)).specular_factor
        assert a[0] == pytest.approx(b2[0], rel=1e-14) and 0.0 < a[0] < 1.0
    # the exact SO: visibility cone cos θ_v = √(1 − ao), specular cone cos θ_s = 10^(−α²), by Monte Carlo
    rng = np.random.default_rng(11)
    w = _unit(rng.normal(size=(400_000, 3)))
    cos_s = 2.0 ** (-3.32193 * 0.36**2)
    in_s = w @ R >= cos_s
    frac = np.count_nonzero(in_s & (w @ b[0] >= math.sqrt(1 - ao[0]))) / np.count_nonzero(in_s)
    so = get("gtso-exact-alpha")(_inputs(v=v, roughness=0.6, ao=ao, bent_normal=b)).specular_factor[0]
    sigma = math.sqrt(so * (1 - so) / np.count_nonzero(in_s))
    assert abs(so - frac) <= 5 * sigma and 0.05 < so < 0.95


def test_filament_gtso_fade():
    v = _unit([0.2, 0.1, 0.95])
    R = _frame_for_reflection(v, [0.0, 0.0, 1.0])
    ao = np.array([0.3])
    theta_v = math.acos(math.sqrt(1 - 0.3))
    b = (math.cos(theta_v) * R + math.sin(theta_v) * _unit(np.cross(R, [1.0, 0.0, 0.0])))[None]  # R on the cone's rim
    for r in (0.05, 0.2, 0.25, 0.3, 0.5):
        alpha = r * r
        raw = get("gtso-smoothstep-alpha")(_inputs(v=v, roughness=r, ao=ao, bent_normal=b)).specular_factor[0]
        faded = get("filament-gtso")(_inputs(v=v, roughness=r, ao=ao, bent_normal=b)).specular_factor[0]
        t = np.clip((alpha - 0.01) / 0.08, 0, 1)
        t = t * t * (3 - 2 * t)
        assert faded == pytest.approx(1 - t + t * raw, abs=1e-15)
        assert raw < 1.0
    assert get("filament-gtso")(_inputs(v=v, roughness=0.05, ao=ao, bent_normal=b)).specular_factor[0] == 1.0
    assert get("filament-gtso")(_inputs(v=v, roughness=0.5, ao=ao, bent_normal=b), fade_alpha=None).specular_factor[0] \
        == get("gtso-smoothstep-alpha")(_inputs(v=v, roughness=0.5, ao=ao, bent_normal=b)).specular_factor[0]


def test_regions_exact():
    vis = np.array([[1.0, 0.25, 0.0], [0.5, 0.5, 0.5]])
    res = get("regions-exact")(_inputs(P=2, region_visibility=vis))
    assert np.array_equal(res.region_weights, vis)
    assert res.diffuse_factor is None and res.specular_factor is None


# ----------------------------------------------------------------------------------------------
# shade()
# ----------------------------------------------------------------------------------------------
def test_shade_factors():
    A1 = np.array([[1.0, 2.0], [3.0, 4.0]])
    S = np.array([[0.5, 0.25], [1.0, 2.0]])
    terms = UnoccludedTerms(kd=0.8, diffuse=A1, specular=S)
    fd, fs = np.array([0.5, 1.0]), np.array([0.0, 0.5])
    assert np.allclose(shade(OcclusionResult(diffuse_factor=fd, specular_factor=fs), terms),
                       0.8 * fd[:, None] * A1 + fs[:, None] * S)
    assert np.allclose(shade(OcclusionResult(), terms), 0.8 * A1 + S)
    fdc = np.array([[0.1, 0.2], [0.3, 0.4]])
    assert np.allclose(shade(OcclusionResult(diffuse_factor=fdc), terms), 0.8 * fdc * A1 + S)
    # a pure specular material needs no diffuse term
    spec = UnoccludedTerms(kd=0.0, diffuse=None, specular=S)
    assert np.allclose(shade(OcclusionResult(diffuse_factor=fd, specular_factor=fs), spec), fs[:, None] * S)


def test_shade_regions_and_transfer():
    rng = np.random.default_rng(5)
    A1, S = rng.uniform(size=(2, 3, 2))
    one = UnoccludedTerms(kd=0.6, diffuse=A1, specular=S, diffuse_regions=A1[:, None], specular_regions=S[:, None])
    assert np.allclose(shade(OcclusionResult(region_weights=np.ones((3, 1))), one), 0.6 * A1 + S)
    # two regions that split the environment, weighted
    Ai = np.stack([0.3 * A1, 0.7 * A1], axis=1)
    Si = np.stack([0.4 * S, 0.6 * S], axis=1)
    two = UnoccludedTerms(kd=0.6, diffuse=A1, specular=S, diffuse_regions=Ai, specular_regions=Si)
    w = np.array([[1.0, 1.0], [0.0, 1.0], [0.5, 0.0]])
    expected = (w[:, 0, None] * (0.6 * Ai[:, 0] + Si[:, 0]) + w[:, 1, None] * (0.6 * Ai[:, 1] + Si[:, 1]))
    assert np.allclose(shade(OcclusionResult(region_weights=w), two), expected)
    assert np.allclose(shade(OcclusionResult(region_weights=np.ones((3, 2))), two), 0.6 * A1 + S)
    # transfer: kd·D + f_s·S
    D = rng.uniform(size=(3, 2))
    fs = np.array([1.0, 0.5, 0.0])
    assert np.allclose(shade(OcclusionResult(diffuse_radiance=D, specular_factor=fs), one), 0.6 * D + fs[:, None] * S)


def test_shade_errors():
    S = np.ones((2, 3))
    terms = UnoccludedTerms(kd=1.0, diffuse=S, specular=S)
    with pytest.raises(IBLError, match="region terms"):
        shade(OcclusionResult(region_weights=np.ones((2, 1))), terms)
    with pytest.raises(IBLError, match="nothing else"):
        shade(OcclusionResult(region_weights=np.ones((2, 1)), specular_factor=np.ones(2)), terms)
    with pytest.raises(IBLError, match="diffuse_factor"):
        shade(OcclusionResult(diffuse_radiance=S, diffuse_factor=np.ones(2)), terms)
    with pytest.raises(IBLError, match="kd != 0"):
        shade(OcclusionResult(), UnoccludedTerms(kd=0.5, diffuse=None, specular=S))
    with pytest.raises(IBLError, match="specular_factor has shape"):
        shade(OcclusionResult(specular_factor=np.ones(3)), terms)
    with pytest.raises(IBLError, match="NaN"):
        shade(OcclusionResult(diffuse_factor=np.array([np.nan, 1.0])), terms)
    with pytest.raises(IBLError, match="kd"):
        shade(OcclusionResult(), UnoccludedTerms(kd=-1.0, diffuse=S, specular=S))


# ----------------------------------------------------------------------------------------------
# PRT
# ----------------------------------------------------------------------------------------------
def _hemisphere_transfer(normals, L=4, n_theta=24, n_phi=32):
    """T_k = ∫ max(n·ω, 0)/π Y_k(ω) dω (V ≡ 1) by Gauss–Legendre in the polar angle about n and the trapezoid rule
    in azimuth (the integrand is smooth in both)."""
    x, wx = np.polynomial.legendre.leggauss(n_theta)
    th = (x + 1) * np.pi / 4                # [0, π/2]
    wth = wx * np.pi / 4
    ph = np.arange(n_phi) * TWO_PI / n_phi
    out = []
    for n in normals:
        t = _unit(np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0]))
        b = np.cross(n, t)
        TH, PH = np.meshgrid(th, ph, indexing="ij")
        w = (np.sin(TH) * np.cos(TH) / np.pi) * wth[:, None] * (TWO_PI / n_phi)
        dirs = (np.cos(TH)[..., None] * n + (np.sin(TH) * np.cos(PH))[..., None] * t
                + (np.sin(TH) * np.sin(PH))[..., None] * b)
        out.append(np.einsum("ij,ijk->k", w, real_sh(dirs.reshape(n_theta, n_phi, 3), L)))
    return np.array(out)


def _sphere_projection(f, L=4, n_theta=24, n_phi=32):
    """L_k = ∫ f(ω) Y_k(ω) dω by Gauss–Legendre in cos θ and the trapezoid rule in φ (exact for low-order f)."""
    mu, wmu = np.polynomial.legendre.leggauss(n_theta)
    ph = np.arange(n_phi) * TWO_PI / n_phi
    MU, PH = np.meshgrid(mu, ph, indexing="ij")
    s = np.sqrt(1 - MU**2)
    dirs = np.stack([s * np.cos(PH), s * np.sin(PH), MU], axis=-1)
    w = wmu[:, None] * (TWO_PI / n_phi) * np.ones_like(PH)
    return np.einsum("ij,ij,ijk->k", w, f(dirs), real_sh(dirs, L))


def test_prt_reproduces_unoccluded_lobe_averages():
    rng = np.random.default_rng(2)
    normals = _unit(rng.normal(size=(5, 3)))
    T = _hemisphere_transfer(normals)                             # (5, 25)
    const = _sphere_projection(lambda d: np.full(d.shape[:-1], 2.0))[:, None]
    linear = _sphere_projection(lambda d: 1.0 + d[..., 2])[:, None]
    env = np.concatenate([const, linear], axis=1)                 # (25, 2): L ≡ 2 and L = 1 + ω_z
    inp = OcclusionInputs(normal=normals, view=normals, roughness=0.5, sh_transfer=T, env_sh=env)
    for name in ("prt-3", "prt-5"):
        res = get(name)(inp)
        assert res.diffuse_radiance.shape == (5, 2) and np.all(res.specular_factor == 1.0)
        assert np.allclose(res.diffuse_radiance[:, 0], 2.0, rtol=0, atol=1e-12)
        assert np.allclose(res.diffuse_radiance[:, 1], 1.0 + 2.0 / 3.0 * normals[:, 2], rtol=0, atol=1e-12)
    # specular="ao" multiplies the specular term by ao and then needs it
    with pytest.raises(IBLError, match="needs the input ao"):
        get("prt-3")(inp, specular="ao")
    ao = np.linspace(0.2, 1.0, 5)
    res = get("prt-3")(OcclusionInputs(normal=normals, view=normals, roughness=0.5, sh_transfer=T, env_sh=env, ao=ao),
                       specular="ao")
    assert np.array_equal(res.specular_factor, ao)


def test_prt_coefficient_counts():
    z = np.array([[0.0, 0.0, 1.0]])
    inp = OcclusionInputs(normal=z, view=z, roughness=0.5, sh_transfer=np.ones((1, 9)), env_sh=np.ones((25, 3)))
    assert get("prt-3")(inp).diffuse_radiance == pytest.approx(np.full((1, 3), 9.0))
    assert get("prt-3")(inp, order=2).diffuse_radiance == pytest.approx(np.full((1, 3), 4.0))
    with pytest.raises(IBLError, match="order 5 needs 25 SH coefficients, but sh_transfer holds 9"):
        get("prt-5")(inp)
    with pytest.raises(IBLError, match="expected order"):
        get("prt-3")(OcclusionInputs(normal=z, view=z, roughness=0.5, sh_transfer=np.ones((1, 10)),
                                     env_sh=np.ones((25, 3))))
    with pytest.raises(IBLError, match="order must be a whole number"):
        get("prt-3")(inp, order=2.5)


# ----------------------------------------------------------------------------------------------
# input checks
# ----------------------------------------------------------------------------------------------
def test_input_checks():
    ao = np.array([0.5, 0.5])
    with pytest.raises(IBLError, match=r"occlusion method 'gtso-exact-alpha' needs the input bent_normal"):
        get("gtso-exact-alpha")(_inputs(P=2, ao=ao))
    with pytest.raises(IBLError, match=r"input ao has shape \(3,\), expected \(2\)"):
        get("ao-both")(_inputs(P=2, ao=np.full(3, 0.5)))
    with pytest.raises(IBLError, match="input ao holds NaN"):
        get("ao-both")(_inputs(P=2, ao=np.array([0.5, np.nan])))
    for bad in (1.1, -0.1):
        with pytest.raises(IBLError, match=r"input ao must lie in \[0, 1\]"):
            get("ao-both")(_inputs(P=2, ao=np.array([0.5, bad])))
    res = get("ao-both")(_inputs(P=2, ao=np.array([1.0 + 1e-13, -1e-13])))  # rounding: accepted, clipped
    assert list(res.diffuse_factor) == [1.0, 0.0]
    with pytest.raises(IBLError, match="input normal must hold unit vectors"):
        get("none")(OcclusionInputs(normal=np.array([[0.0, 0.0, 1.01]]), view=np.array([[0.0, 0.0, 1.0]]),
                                    roughness=0.5))
    with pytest.raises(IBLError, match=r"input view has shape \(2, 3\), expected \(1, 3\)"):
        get("none")(OcclusionInputs(normal=np.array([[0.0, 0.0, 1.0]]), view=np.tile([0.0, 0.0, 1.0], (2, 1)),
                                    roughness=0.5))
    with pytest.raises(IBLError, match=r"input bent_normal has shape \(1, 3\), expected \(2, 3\)"):
        get("gtso-exact-r")(_inputs(P=2, ao=ao, bent_normal=np.array([[0.0, 0.0, 1.0]])))
    with pytest.raises(IBLError, match="input region_visibility must lie"):
        get("regions-exact")(_inputs(P=1, region_visibility=np.array([[0.5, 2.0]])))
    with pytest.raises(IBLError, match="input albedo"):
        get("multibounce-ao")(_inputs(P=2, ao=ao, albedo=np.ones((3, 3))))
    for r in (-0.1, 1.5, np.nan, True):
        with pytest.raises(IBLError, match="roughness"):
            get("lagarde2014-alpha")(_inputs(P=2, roughness=r, ao=ao))
    with pytest.raises(IBLError, match="inputs must be an OcclusionInputs"):
        get("none")({"normal": [[0, 0, 1]]})


def test_parameter_checks_and_unknown_names():
    inp = _inputs(P=1, ao=np.array([0.5]), bent_normal=np.array([[0.0, 0.0, 1.0]]),
                  geo_normal=np.array([[0.0, 0.0, 1.0]]))
    with pytest.raises(IBLError, match=r"occlusion method 'horizon-k1.1': unknown parameter\(s\) 'normal'; it takes k"):
        get("horizon-k1.1")(inp, normal="shading")
    with pytest.raises(IBLError, match="it takes no parameters"):
        get("none")(inp, k=1)
    with pytest.raises(IBLError, match=r"occlusion method 'horizon-k1.3': parameter k must be a finite number > 0"):
        get("horizon-k1.3")(inp, k=-1.0)
    with pytest.raises(IBLError, match="parameter intersection must be one of 'smoothstep', 'exact'"):
        get("gtso-exact-r")(inp, intersection="mc")
    with pytest.raises(IBLError, match="parameter roughness_input"):
        get("lagarde2014-alpha")(inp, roughness_input="r")
    with pytest.raises(IBLError, match="fade_alpha"):
        get("filament-gtso")(inp, fade_alpha=(0.09, 0.01))
    with pytest.raises(IBLError, match="unknown occlusion method 'gtao'; choose one of none, ao-diffuse"):
        get("gtao")
    assert get("horizon-k1.1")(inp, k=2.0).specular_factor[0] == 1.0


def test_per_pixel_roughness():
    v = np.tile(_unit([0.6, 0.0, 0.8]), (3, 1))
    inp = OcclusionInputs(normal=np.tile([0.0, 0.0, 1.0], (3, 1)), view=v, roughness=np.array([0.1, 0.5, 0.9]),
                          ao=np.full(3, 0.4))
    per_pixel = get("lagarde2014-r")(inp).specular_factor
    for i, r in enumerate([0.1, 0.5, 0.9]):
        one = get("lagarde2014-r")(OcclusionInputs(normal=inp.normal[:1], view=v[:1], roughness=r, ao=inp.ao[:1]))
        assert per_pixel[i] == one.specular_factor[0]


def test_compute_sees_only_the_inputs_it_needs():
    seen = {}

    def spy(inputs):
        seen.update({f: getattr(inputs, f) is not None for f in INPUT_FIELDS})
        return OcclusionResult(diffuse_factor=inputs.ao)

    m = OcclusionMethod("spy", ("ao",), spy, {}, "test", "records its inputs")
    full = _random_inputs(np.random.default_rng(0), P=4)
    m(full)
    assert seen == {f: f == "ao" for f in INPUT_FIELDS}
    with pytest.raises(IBLError, match="needs names no OcclusionInputs field: shadow"):
        OcclusionMethod("bad", ("shadow",), spy, {}, "", "")


# ----------------------------------------------------------------------------------------------
# registry
# ----------------------------------------------------------------------------------------------
def _random_inputs(rng, P=64, C=3, R=4, order=5):
    n = _unit(rng.normal(size=(P, 3)))
    v = _unit(rng.normal(size=(P, 3)))
    v = np.where((np.einsum("pi,pi->p", n, v) < 0)[:, None], -v, v)  # mostly in front; a few grazing below
    v[:3] = _unit(v[:3] - 1.2 * n[:3])                               # some normals facing away from the view
    ao = rng.uniform(size=P)
    ao[:4] = [0.0, 1.0, 0.0, 1.0]
    k = order * order
    return OcclusionInputs(normal=n, view=v, roughness=0.4, geo_normal=_unit(n + 0.5 * rng.normal(size=(P, 3))),
                           ao=ao, bent_normal=_unit(n + 0.3 * rng.normal(size=(P, 3))),
                           albedo=rng.uniform(size=C), region_visibility=rng.uniform(size=(P, R)),
                           sh_transfer=rng.normal(size=(P, k)) * 0.1, env_sh=rng.normal(size=(k, C)),
                           sh_transfer_matrix=rng.normal(size=(P, k, k)) * 0.1)


def test_registry_entries_are_well_formed_and_callable():
    assert len(OCCLUSION_METHODS) == 20
    rng = np.random.default_rng(9)
    full = _random_inputs(rng)
    for name, m in OCCLUSION_METHODS.items():
        assert m.name == name and m.summary and m.citation
        assert set(m.needs) <= set(INPUT_FIELDS), name
        with pytest.raises(TypeError):
            m.params["x"] = 1
        for roughness in (0.0, 0.4, 1.0):
            res = m(dataclasses.replace(full, roughness=roughness))
            assert isinstance(res, OcclusionResult)
            for f in (res.diffuse_factor, res.specular_factor, res.region_weights):
                if f is not None:
                    assert f.shape[0] == 64 and np.all(np.isfinite(f)), name
                    # ≤ 1, but for multi-bounce AO's published fit, which reaches 1 + 5e-4 ρ − 4e-4 at V = 1
                    assert np.all(f >= 0.0) and np.all(f <= 1.0 + 1e-4), name
            for radiance in (res.diffuse_radiance, res.specular_radiance):
                if radiance is not None:
                    assert radiance.shape == (64, 3) and np.all(np.isfinite(radiance))
        # every declared input is needed: leaving one out names it
        for field in m.needs:
            with pytest.raises(IBLError, match=f"'{name}' needs the input {field}"):
                m(dataclasses.replace(full, **{field: None}))
        # and nothing else is read: the declared inputs alone suffice
        m(OcclusionInputs(normal=full.normal, view=full.view, roughness=0.4, **{f: getattr(full, f) for f in m.needs}))

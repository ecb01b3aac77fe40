"""``convolve(method="auto")`` on real light probes at native size: the planner takes the fast routes.

The probes are the CC0 lat-long files of ``../shared/probes/`` next to the project (1024×512 → 256² faces); without
them the tests are skipped.  Deterministic: the planner's choices and its model costs (``plan_routes``) are
compared, not timings — the wall times of the same comparison are measured by
``benchmarks/bench_convolution.py --probes``.  One run at a reduced size checks that what the planner promised
(the SH band limits at its estimated output floor) holds a posteriori.
"""

from pathlib import Path

import numpy as np
import pytest

from ibl_ref.groundtruth.convolve import convolve, plan_routes
from ibl_ref.groundtruth.sh_bounds import SH_L_MAX

PROBES = Path(__file__).resolve().parents[1].parent / "shared" / "probes"
FILES = sorted(PROBES.glob("*.exr")) if PROBES.is_dir() else []
S = [1.0, 16.0, 256.0]
needs_probes = pytest.mark.skipif(not FILES, reason=f"no real probes in {PROBES} (CC0 lat-long EXR files)")


def _kernels():
    from ibl_ref.groundtruth.kernels import numba_available

    return ["numpy", "compiled"] if numba_available() else ["numpy"]


@pytest.fixture(scope="module")
def probes():
    from ibl_ref.environment.exr_io import load_cube

    return {f.stem: load_cube(f) for f in FILES}


@needs_probes
@pytest.mark.parametrize("kernel", _kernels())
def test_auto_routes_probes_to_the_fast_methods(probes, kernel):
    """Before, the SH planner's band-4 preview of the output rang below zero on probes with a dark ground, it
    found no band limit ≤ 160 for s = 16 and 256 and sent them to the sparse gather (212–489 s, where the SH pass
    takes 21–24 s).  Now: both exponents have a planned band limit, s = 16 goes to the SH pass, and the plan's
    model cost is within 1.2× of the cheapest forced method that meets rtol for every exponent (exact or sparse)
    and within 1.2× of "the SH pass for every exponent it can bound, the moment route for the others" (what a user
    forcing methods exponent by exponent would pick: forcing SH for s = 1 misses rtol by far)."""
    for name, cube in probes.items():
        r = plan_routes(cube, S, rtol=1e-3, kernel=kernel)
        L = r["info"]["sh_plan_L_per_s"]
        assert L[16.0] is not None and L[256.0] is not None and max(L[16.0], L[256.0]) <= SH_L_MAX, (name, L)
        assert r["route"][16.0] == "sh" and r["route"][1.0] == "moment", (name, r["route"])
        c = r["model_costs_s"]
        assert c["auto"] <= 1.2 * min(c["exact"], c["sparse"]), (name, c)
        from ibl_ref.groundtruth import convolve as cv
        from ibl_ref.groundtruth.moment_convolution import moment_leaf

        n = cube.shape[1]
        mixed = c["sh"] + cv._moment_cost(n, n, moment_leaf(n, 1e-3), kernel) * cv._seconds_per_unit()
        assert c["auto"] <= 1.2 * mixed, (name, c, mixed)


@needs_probes
def test_planned_band_limits_hold_on_a_probe():
    """At 64² faces (the same file, resampled) the SH pass the planner chose meets rtol a posteriori (no fallback
    to the sparse gather) and its floor estimate is below the darkest output texel of every SH exponent."""
    from ibl_ref.environment.exr_io import load_cube

    f = next((p for p in FILES if p.stem == "courtyard"), FILES[0])
    cube = load_cube(f, size=64)
    res = convolve(cube, S, rtol=1e-3, kernel="numpy", workers=1)
    sh = [s for s in S if res.method_used[s] == "sh"]
    assert 16.0 in sh, res.method_used
    assert "fallback_from_sh" not in res.info
    for s in S:
        assert res.error_bound[s].max() <= 1e-3, (s, res.method_used[s])
    floor = res.info["sh_plan_floor"]
    for s in sh:
        assert floor[s] <= float(np.min(res.maps[s])), (s, floor[s], float(np.min(res.maps[s])))

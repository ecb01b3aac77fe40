"""The convergence experiment (ibl_ref.experiments.convergence) runs, writes its files and shows the
discretisation orders documented in phong_convolution (targets are closed forms, see the module)."""

from ibl_ref.atomic import read_csv
from ibl_ref.experiments import convergence


def test_convergence_quick_run_and_plot(tmp_path):
    # smaller grids than the real quick run (test time budget; the experiment's parameters); same code path
    summary = convergence.run(tmp_path, quick=True, face_sizes=(4, 8, 16), ss_face_size=4, ss_factors=(1, 2, 4),
                              ss_reference=8)
    rows = read_csv(tmp_path / "convergence_resolution.csv")
    assert len(rows) == 3 * len(convergence.EXPONENTS)
    # second-order convergence for a resolved lobe (s = 16): observed 3.06 (4→8), 1.91 (8→16);
    # clamped cosine (s = 1): ~1.6 because of the kink at the horizon.  Margins of 0.2-0.3.
    assert min(summary["observed_orders_max_err"]["16.0"]) > 1.7
    assert min(summary["observed_orders_max_err"]["1.0"]) > 1.3
    ss = read_csv(tmp_path / "convergence_supersample.csv")
    # supersampling refines the quadrature of Σ cos^s Ω → 2π/(s+1) (exact target) for s = 16
    w16 = [float(r["weight_rel_err_max"]) for r in ss if float(r["s_phong"]) == 16.0]
    assert all(b < a / 2.5 for a, b in zip(w16, w16[1:])), w16
    paths = convergence.plot(tmp_path)
    assert all(p.exists() and p.stat().st_size > 1000 for p in paths)

"""Benchmark of the geometry pass (ibl_ref.rendering.raster / vsm / raycast), Knuth et al. 2014 Sec. 3.3–3.4.

Prints:
* rasterization time of the teapot (tessellation of ibl_ref.synthetic.synthetic_meshes, ~16k triangles) at 256² (G-buffer
  and depth only), with the cost of projecting the vertices as the in-run baseline (ratio raster / projection);
* exact directional visibility with the binned parallel-ray test (points/s), for comparison;
* rays/s of trimesh's ray backend (embree or the pure-NumPy fallback) on the same mesh, and the ratio of
  ray-cast primary visibility time to raster time;
* VSM precision: max |visibility − float64 VSM visibility| on the teapot-on-ground scene for float32 and float16
  moments (the paper's RG16F), the max error of M2 − M1² per dtype, and the difference to the exact (hard)
  visibility of the same light direction (includes the intended penumbra softening).

Run:  OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 python benchmarks/bench_raster.py [--size 256] [--rays 2000]
"""

from __future__ import annotations

import argparse
import time

import numpy as np


def _best_of(fn, repeat):
    best = np.inf
    out = None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=256, help="image size (square), default 256")
    ap.add_argument("--rays", type=int, default=2000, help="rays for the ray-backend speed test, default 2000")
    ap.add_argument("--repeat", type=int, default=3, help="best of N timings, default 3")
    ap.add_argument("--render", action="store_true",
                    help="also render Eq. 5 (teapot on ground, sky_sun, 24 PEMs, 96²) with VSM fp32/fp16 and exact "
                         "visibility and print the image errors")
    args = ap.parse_args(argv)

    from ibl_ref.rendering import raycast, vsm
    from ibl_ref.rendering.camera import PerspectiveCamera
    from ibl_ref.rendering.raster import prepare_scene, rasterize, render_depth
    from ibl_ref.synthetic.synthetic_meshes import make_mesh

    teapot = make_mesh("teapot")
    scene = prepare_scene(teapot)
    c, r = scene.bounds()
    cam = PerspectiveCamera(eye=c + r * np.array([1.2, 1.0, 2.2]), target=c, up=[0, 1, 0], fov_y_deg=40,
                            width=args.size, height=args.size)
    print(f"teapot: {len(scene.faces)} triangles, image {args.size}², timings under load (shared machine)")
    t_proj, _ = _best_of(lambda: cam.project(scene.vertices), args.repeat)
    t_gbuf, g = _best_of(lambda: rasterize(scene, cam), args.repeat)
    t_depth, _ = _best_of(lambda: render_depth(scene, cam), args.repeat)
    print(f"  project vertices        {t_proj * 1e3:8.2f} ms (baseline)")
    print(f"  rasterize G-buffer      {t_gbuf * 1e3:8.2f} ms  ratio {t_gbuf / t_proj:7.0f}x baseline, "
          f"{g.mask.sum()} covered px")
    print(f"  render_depth            {t_depth * 1e3:8.2f} ms")

    rps = raycast.measure_rays_per_s(teapot, n_rays=args.rays)
    est = args.size**2 / rps
    print(f"ray backend: {raycast.backend()}  {rps:,.0f} rays/s on the teapot "
          f"(primary rays at {args.size}² would take ~{est:.1f} s = {est / t_gbuf:,.0f}x the rasterizer)")

    # VSM precision: teapot on a ground quad, one light, errors vs float64 moments
    import trimesh

    lo, hi = teapot.bounds
    s = 1.5 * (hi - lo).max()
    y0 = lo[1]
    ground = trimesh.Trimesh([[-s, y0, -s], [s, y0, -s], [s, y0, s], [-s, y0, s]], [[0, 2, 1], [0, 3, 2]],
                             process=False)
    meshes = [(teapot, 0), (ground, 1)]
    L = np.array([0.4, 1.0, 0.3])
    L /= np.linalg.norm(L)
    gb = rasterize(meshes, PerspectiveCamera(eye=c + r * np.array([0.5, 1.8, 2.5]), target=c, up=[0, 1, 0],
                                             fov_y_deg=50, width=128, height=128))
    pts = gb.position[gb.mask]
    t0 = time.perf_counter()
    exact = raycast.parallel_visibility(meshes, pts, L, normals=gb.face_normal[gb.mask])
    t_ex = time.perf_counter() - t0
    print(f"exact parallel-ray visibility (binned): {len(pts)} points in {t_ex * 1e3:.0f} ms "
          f"= {len(pts) / t_ex:,.0f} points/s ({len(pts) / t_ex / rps:,.0f}x trimesh rays/s)")
    ref = None
    print(f"VSM 512², Ω = 0.05 sr, {len(pts)} visible receiver points:")
    for dt in ("float64", "float32", "float16"):
        t_vsm, m = _best_of(lambda: vsm.build_vsm(meshes, L, 0.05, resolution=512, dtype=dt), 1)
        v = vsm.visibility(pts, m)
        var = m.moments[..., 1].astype(float) - m.moments[..., 0].astype(float) ** 2
        if ref is None:
            ref, var_ref = v, var
        print(f"  {dt:8s} build {t_vsm * 1e3:7.1f} ms  max|vis − f64| = {np.abs(v - ref).max():.2e}  "
              f"mean = {np.abs(v - ref).mean():.2e}  max|var − f64| = {np.abs(var - var_ref).max():.2e}  "
              f"(σ = {m.sigma_texels:.2f} texels)  vs exact hard: mean|Δ| = {np.abs(v - exact).mean():.3f}, "
              f"|Δ| > 0.5 on {np.mean(np.abs(v - exact) > 0.5) * 100:.1f} % of points")
    # the usual fp16 remedy: a larger σ²_min (hides the rounding noise of M2 − M1², softens contact shadows)
    for mv in (1e-5, 1e-4, 1e-3):
        a = vsm.visibility(pts, vsm.build_vsm(meshes, L, 0.05, resolution=512, dtype="float64", min_variance=mv))
        b = vsm.visibility(pts, vsm.build_vsm(meshes, L, 0.05, resolution=512, dtype="float16", min_variance=mv))
        print(f"  float16 vs float64 at σ²_min = {mv:.0e}: max|Δvis| = {np.abs(a - b).max():.2e}  "
              f"mean = {np.abs(a - b).mean():.2e}")

    if args.render:
        from ibl_ref.knuth2014.pem import build_pems
        from ibl_ref.rendering.render import render_pem
        from ibl_ref.synthetic.synthetic_envs import make_env

        pems = build_pems(make_env("sky_sun", n=32), n_lights=24)
        rcam = PerspectiveCamera(eye=c + r * np.array([1.0, 1.0, 2.4]), target=c, up=[0, 1, 0], fov_y_deg=40,
                                 width=96, height=96)
        gloss = {0: 0.8, 1: 0.2}
        t0 = time.perf_counter()
        ex = render_pem(meshes, rcam, pems, gloss, visibility="raycast")
        t_ex = time.perf_counter() - t0
        exh = render_pem(meshes, rcam, pems, gloss, visibility="raycast", horizon=True)
        print("Eq. 5 render 96², 24 PEMs (sky_sun 32²), teapot g=0.8 + ground g=0.2; errors vs exact visibility:")
        print(f"  exact visibility (binned)  {t_ex:6.2f} s")
        mask = ex.mask
        for dt in ("float32", "float16"):
            t0 = time.perf_counter()
            rv = render_pem(meshes, rcam, pems, gloss, visibility="vsm", vsm_resolution=512, vsm_dtype=dt)
            t_v = time.perf_counter() - t0
            d = np.abs(rv.image - ex.image)[mask].mean(axis=-1)
            ref = ex.image[mask].mean(axis=-1)
            print(f"  VSM {dt:8s}               {t_v:6.2f} s  mean|Δ|/mean = {d.mean() / ref.mean():.3f}  "
                  f"99th pct |Δ|/mean = {np.percentile(d, 99) / ref.mean():.3f}")
        d = np.abs(ex.unshadowed - ex.image)[mask].mean(axis=-1)
        print(f"  no shadows (VIS = 1)               mean|Δ|/mean = {d.mean() / ex.image[mask].mean():.3f}")
        d = np.abs(exh.image - ex.image)[mask].mean(axis=-1)
        print(f"  horizon term (exact with vs without) mean|Δ|/mean = {d.mean() / ex.image[mask].mean():.3f}")


if __name__ == "__main__":
    main()

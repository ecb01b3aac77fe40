"""Kán et al. (2015), Table 1: time to compute 8 reflection maps at once vs output resolution.

Kán, Unterguggenberger & Kaufmann (2015), *High-Quality Consistent Illumination in Mobile Augmented
Reality by Radiance Convolution on the GPU*, Table 1: "Computational time of reflection maps calculation
for different output resolutions. Eight reflection maps were calculated simultaneously", measured on an
NVIDIA Shield tablet (OpenGL ES 3.0 fragment shaders, every input pixel for every output pixel; the
input map size is not stated).  Published times (min:s:ms): 32×32 00:00:040, 64×64 00:01:450,
128×128 00:06:360, 256×256 00:28:090, 512×512 02:38:370, 1024×1024 23:01:650.

Here: the same task on this CPU — 8 Phong exponents {1, 2, 5, 10, 20, 50, 100, 1000} for a cube map
whose input and output face size are both N, on the sky + 1e5 sun environment — with
:func:`ibl_ref.groundtruth.convolve.convolve` ``method="auto"`` at rtol 1e-3 (per-exponent method and its reported
bound in the CSV) and, where affordable (N ≤ 32, or N ≤ 64 in the full run), the exact gather.  Kán's
"resolution" is the size of one output map (their maps are spherical, ours are cube faces: a face of N²
texels has 6N² texels in total) — the comparison is of orders of magnitude, not like for like.
Wall-clock and CPU times are recorded (CPU: this process and ``convolve``'s forked workers; the plot uses
CPU time, robust on a shared machine); the published ones are from a 2015 mobile GPU.  Full run: N = 32 … 256
(40 s on 2 cores).

Outputs ``kan_table1.csv``, ``kan_table1.json``; plot ``kan_table1.png``.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from ..progress import track
from ..atomic import read_csv, write_csv, write_json
from . import Param, resolve_params
from ..figures import pyplot
from ..figures import save_figure
from ..groundtruth.convolve import convolve
from ..groundtruth.phong_convolution import convolve_exact_many
from ..synthetic.synthetic_envs import SUN_NEAR_CORNER
from ..synthetic.synthetic_envs import make_env

NAME = "kan-table1"
DESCRIPTION = "time for 8 exponents at once vs face size, next to Kán et al. 2015 Table 1 (mobile GPU)"
PAPER = "Kan et al. 2015, Table 1 (time to prefilter 8 Phong exponents at once vs map resolution)"
IN_QUICK_REPRODUCE = True
PARAMS = (Param("face_sizes", (32, 64, 128, 256), (16, 32), "cube face sizes N"),
          Param("exact_max", 64, 32, "largest face size also timed with the exact dense gather"))
RUNTIME = {"quick": "1.7 s (load 0.3)", "full": "3 min 36 s (load 11; 73 s CPU)"}
OUTPUTS = ("kan_table1.csv", "kan_table1.json", "kan_table1.png")

EXPONENTS = (1.0, 2.0, 5.0, 10.0, 20.0, 50.0, 100.0, 1000.0)
#: Kán et al. 2015, Table 1 (output resolution → seconds; NVIDIA Shield tablet, 8 maps at once)
KAN_TABLE1_S = {32: 0.040, 64: 1.450, 128: 6.360, 256: 28.090, 512: 158.370, 1024: 1381.650}
CITATION = "Kan, Unterguggenberger, Kaufmann 2015, Table 1 (NVIDIA Shield tablet, OpenGL ES 3.0)"


def run(out_dir: Path, quick: bool = False, **params) -> dict:

    def environment(n):  # the speed-accuracy environment: sky + a 1e5 sun near a cube corner
        return make_env("sky_sun", n, sun_direction=SUN_NEAR_CORNER, sun_radiance=1e5)

    out_dir = Path(out_dir)
    p = resolve_params(__name__, quick, params)
    sizes, exact_max = p["face_sizes"], p["exact_max"]
    convolve(environment(4), [2.0, 64.0], method="auto")  # warm-up: imports and scipy set-up not timed
    rows = []
    for n in track(sizes, "kan-table1: face sizes", unit="size"):
        cube = environment(n)
        t0 = time.perf_counter()
        res = convolve(cube, EXPONENTS, method="auto", rtol=1e-3)
        # CPU of this process and of convolve's forked workers (process_time alone misses them)
        t_auto, c_auto = time.perf_counter() - t0, res.timings_s["total_cpu"]
        t_exact = c_exact = float("nan")
        if n <= exact_max:
            t0, c0 = time.perf_counter(), time.process_time()
            convolve_exact_many(cube, EXPONENTS)
            t_exact, c_exact = time.perf_counter() - t0, time.process_time() - c0
        bmax = max(float(b.max()) for b in res.error_bound.values())
        rows.append(
            {
                "face_size_texels": n,
                "n_exponents": len(EXPONENTS),
                "time_auto_s": round(t_auto, 4),
                "cpu_time_auto_s": round(c_auto, 4),
                "time_exact_s": round(t_exact, 4) if np.isfinite(t_exact) else "",
                "cpu_time_exact_s": round(c_exact, 4) if np.isfinite(c_exact) else "",
                "auto_rel_bound_max": bmax,
                "auto_methods": " ".join(f"{s:g}:{res.method_used[s]}" for s in EXPONENTS),
                "kan2015_time_s": KAN_TABLE1_S.get(n, ""),
            }
        )
    for n, t in KAN_TABLE1_S.items():
        if n not in sizes:
            rows.append({"face_size_texels": n, "n_exponents": 8, "time_auto_s": "", "cpu_time_auto_s": "",
                         "time_exact_s": "", "cpu_time_exact_s": "",
                         "auto_rel_bound_max": "", "auto_methods": "", "kan2015_time_s": t})
    rows.sort(key=lambda r: r["face_size_texels"])
    write_csv(out_dir / "kan_table1.csv", rows, list(rows[0].keys()),
              comment=f"8 Phong exponents {list(EXPONENTS)} at once; this CPU (shared) vs {CITATION}\n"
                      "face_size_texels = our cube face size N (input = output) / Kan's output map resolution")
    summary = {"exponents": list(EXPONENTS), "sizes": list(sizes), "citation": CITATION,
               "rows": [r for r in rows if r["time_auto_s"] != ""]}
    write_json(out_dir / "kan_table1.json", summary)
    return summary


def plot(out_dir: Path) -> list:

    plt = pyplot()

    out_dir = Path(out_dir)
    rows = read_csv(out_dir / "kan_table1.csv")
    fig, ax = plt.subplots(figsize=(5.5, 4))
    for key, label, style in (("cpu_time_auto_s", "ibl_ref auto (rtol 1e-3), CPU s summed over cores", "o-"),
                              ("cpu_time_exact_s", "ibl_ref exact, CPU s summed over cores", "s--"),
                              ("kan2015_time_s", "Kán et al. 2015 Table 1, mobile GPU", "^:")):
        pts = [(int(r["face_size_texels"]), float(r[key])) for r in rows if r[key] not in ("", "nan")]
        if pts:
            x, y = zip(*pts)
            ax.plot(x, y, style, label=label)
    ax.set(xscale="log", yscale="log", xlabel="face size / output resolution N",
           ylabel="time for 8 exponents (s)", title="8 reflection maps at once")
    ax.set_xticks([16, 32, 64, 128, 256, 512, 1024])
    ax.set_xticklabels(["16", "32", "64", "128", "256", "512", "1024"])
    ax.legend(fontsize=7)
    fig.tight_layout()
    p = out_dir / "kan_table1.png"
    save_figure(fig, p, dpi=110)
    return [p]

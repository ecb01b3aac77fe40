"""Time and peak memory of real-probe sizes: read → lat-long to cube → median cut, against the goals.

Run:  python benchmarks/bench_probe_sizes.py [--sizes 1k 4k 16k] [--out results/bench_probe_sizes.csv]
      python benchmarks/bench_probe_sizes.py --kernels      # balance of the conservative kernel vs H

Each size runs in its own process (fresh peak RSS).  A synthetic probe like a published one (2:1
lat-long float32 RGB: sky gradient, dark ground with a black strip, a 0.5° sun of 3e4; DWAB-compressed, no ``envmap``
attribute) is written to a temporary folder, then the steps of ``ibl-ref mediancut PROBE --size N``
are timed one by one:

* ``read``: :func:`ibl_ref.environment.exr_io.read_image` as float32 with the radiance policy (DWAB's negatives
  are clamped and reported);
* ``to-cube``: :func:`ibl_ref.environment.resample.latlong_to_cube` to face N (the conservative kernel; inputs
  with H ≥ 4N are block-reduced exactly to H ≥ 2N first);
* ``mediancut``: :func:`ibl_ref.knuth2014.median_cut.median_cut` with 24 lights (per-face variant), for faces up
  to 1024² (median_cut's own working set is ~280 bytes per texel: 1.9 GB at 1024², so 7 GB at 2048²).

``cpu_s`` (to-cube) is the CPU time of the process, which depends less on the load than the wall time.
Peak RSS is sampled every 5 ms by a thread reading ``/proc/self/statm`` (the whole process, input
included); ``rel_int_change`` is the relative change of ∫L dω from the float32 input to the cube (max
over channels).  Goals: 4K → face 1024 in ≤ 10 s and ≤ 1.5 GB; 16K → face 2048 in ≤ 120 s
and ≤ 3× the decoded input.  Timings depend on the load of the machine: the script prints ``uptime``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

SIZES = {"1k": (512, 256), "4k": (2048, 1024), "16k": (8192, 2048), "16k-small": (8192, 256)}
MEDIANCUT_MAX_FACE = 1024  # median_cut itself (not the resampling) needs ~280 B per texel
GOALS = {"4k": (10.0, 1.5 * 2**30), "16k": (120.0, None)}  # to-cube seconds, peak bytes (16k: 3x input)


def _rss() -> int:
    with open("/proc/self/statm") as fh:
        return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


class Peak:
    """Peak RSS over a block, sampled every 5 ms."""

    def __enter__(self):
        self.peak = _rss()
        self._stop = False
        self._t = threading.Thread(target=self._run, daemon=True)
        self._t.start()
        self.t0 = time.perf_counter()
        self.c0 = time.process_time()
        return self

    def _run(self):
        while not self._stop:
            self.peak = max(self.peak, _rss())
            time.sleep(0.005)

    def __exit__(self, *exc):
        self.seconds = time.perf_counter() - self.t0
        self.cpu_seconds = time.process_time() - self.c0  # CPU of this process: a proxy less sensitive to load
        self._stop = True
        self._t.join()
        self.peak = max(self.peak, _rss())


def make_probe_planes(h: int, sun: float = 3e4, sun_radius_deg: float = 0.5):
    """R, G, B float32 planes (h, 2h) of the synthetic probe, built in row blocks (no float64 copy)."""
    w = 2 * h
    planes = [np.empty((h, w), np.float32) for _ in range(3)]
    edges = np.pi / 2 - np.pi * np.arange(h + 1) / h
    lat = 0.5 * (edges[1:] + edges[:-1])
    lon = np.pi - (np.arange(w) + 0.5) * 2 * np.pi / w
    d = np.array([0.3, 0.55, -0.78])
    d /= np.linalg.norm(d)
    cos_r = np.cos(np.radians(sun_radius_deg))
    rng = np.random.default_rng(0)
    colour = (1.0, 0.9, 0.75)
    step = max(1, (1 << 22) // w)
    for r0 in range(0, h, step):
        r1 = min(h, r0 + step)
        la = lat[r0:r1, None]
        y = np.sin(la)
        base = np.where(y > 0, 0.4 + 1.2 * y, 0.05 * (0.2 + 0.8 * rng.random((r1 - r0, w)))) * np.ones((1, w))
        base[(la[:, 0] < -0.3) & (la[:, 0] > -0.4), : w // 4] = 0.0  # a black strip: DWAB rings below 0 there
        cosang = np.cos(la) * (np.sin(lon)[None] * d[0] + np.cos(lon)[None] * d[2]) + y * d[1]
        sunm = cosang >= cos_r
        for c in range(3):
            planes[c][r0:r1] = np.where(sunm, sun * colour[c], base)
    return planes


def _integral_latlong_chunked(img) -> np.ndarray:
    from ibl_ref.environment import envmap

    h, w = img.shape[:2]
    om = envmap.latlong_solid_angles(h, w)[:, 0]
    tot = np.zeros(img.shape[2])
    for r0 in range(0, h, 256):
        tot += np.einsum("ijc,i->c", img[r0 : r0 + 256].astype(np.float64), om[r0 : r0 + 256])
    return tot


def run_one(name: str, compression: str, lights: int) -> list:
    from ibl_ref.environment import exr_io, resample
    from ibl_ref.knuth2014.median_cut import median_cut

    h, n = SIZES[name]
    rows = []

    def log(msg):
        print(f"[{name}] {time.strftime('%H:%M:%S')} {msg} (RSS {_rss() / 2**20:.0f} MiB)", file=sys.stderr, flush=True)

    with tempfile.TemporaryDirectory(prefix="bench_probe_") as tmp:
        path = Path(tmp) / f"probe_{name}.exr"
        with Peak() as p:
            planes = make_probe_planes(h)
            exr_io.write_exr(path, exr_io.ExrPart(list(planes), ("R", "G", "B")), compression=compression)
            del planes
        rows.append(dict(size=name, step="make+write", seconds=p.seconds, peak_rss_bytes=p.peak))
        log(f"written {path.stat().st_size / 2**20:.0f} MiB; make+write peak {p.peak / 2**20:.0f} MiB")
        with Peak() as p:
            img, _, _, _, rep = exr_io.read_image(path, dtype=np.float32, return_report=True)
        decoded = img.nbytes
        rows.append(dict(size=name, step="read", seconds=p.seconds, peak_rss_bytes=p.peak,
                         negatives_clamped=rep.n_negative, removed_fraction=rep.removed_fraction))
        log(f"read peak {p.peak / 2**20:.0f} MiB in {p.seconds:.1f} s")
        src = _integral_latlong_chunked(img)
        resample._KERNELS.clear()
        with Peak() as p:
            cube = resample.latlong_to_cube(img, n)
        rel = float(np.max(np.abs(resample.integral_cube(cube) / src - 1)))
        rows.append(dict(size=name, step=f"to-cube {n}", seconds=p.seconds, peak_rss_bytes=p.peak,
                         rel_int_change=rel, prereduce=resample.prereduce_factor(h, n)))
        rows[-1]["cpu_seconds"] = p.cpu_seconds
        log(f"to-cube peak {p.peak / 2**20:.0f} MiB in {p.seconds:.1f} s ({p.cpu_seconds:.1f} s CPU)")
        del img
        if n > MEDIANCUT_MAX_FACE:
            log(f"mediancut skipped: median_cut needs ~280 bytes per texel (1.9 GB at 1024² faces), "
                f"{280 * 6 * n * n / 2**30:.1f} GB at {n}²")
        else:
            with Peak() as p:
                median_cut(cube, lights, "per-face")
            rows.append(dict(size=name, step=f"mediancut {lights}", seconds=p.seconds, peak_rss_bytes=p.peak))
    for r in rows:
        r["decoded_input_bytes"] = decoded
    return rows


def kernels():
    from ibl_ref.environment import resample

    print(f"{'H':>5} {'N':>5} {'ks':>3} {'iters':>5} {'energy_error_ll':>16} {'energy_error_cube':>18} {'build_s':>8}")
    for h in (16, 64, 256, 512, 1024, 2048):
        n = h // 2
        t = time.perf_counter()
        k = resample.conservative_kernel(h, n)
        dt = time.perf_counter() - t
        print(f"{h:5d} {n:5d} {k.ks:3d} {k.iters:5d} {k.energy_error_ll:16.2e} {k.energy_error_cube:18.2e} {dt:8.2f}")
        resample._KERNELS.clear()


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sizes", nargs="+", default=["1k", "4k"], choices=tuple(SIZES),
                    help="probe sizes (1k = 1024x512 → face 256, 4k → 1024, 16k → 2048, 16k-small → 256)")
    ap.add_argument("--compression", default="dwab", help="EXR compression of the probe (default dwab)")
    ap.add_argument("--lights", type=int, default=24)
    ap.add_argument("--out", default=None, help="CSV file for the rows (units in the column names)")
    ap.add_argument("--kernels", action="store_true", help="print the conservative kernel's balance vs H instead")
    ap.add_argument("--child", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.kernels:
        kernels()
        return 0
    if args.child:
        print(json.dumps(run_one(args.child, args.compression, args.lights)))
        return 0
    print("load:", subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip())
    all_rows = []
    for name in args.sizes:
        res = subprocess.run([sys.executable, __file__, "--child", name, "--compression", args.compression,
                              "--lights", str(args.lights)], stdout=subprocess.PIPE, text=True)
        if res.returncode:
            print(res.stderr, file=sys.stderr)
            return res.returncode
        all_rows.extend(json.loads(res.stdout.strip().splitlines()[-1]))
    print(f"{'size':9s} {'step':16s} {'time_s':>8} {'cpu_s':>7} {'peak_rss_MiB':>13} {'x_input':>8}  notes")
    for r in all_rows:
        note = ""
        if r["step"].startswith("to-cube"):
            note = f"integral rel. change {r['rel_int_change']:.1e}, prereduce x{r['prereduce']}"
            goal = GOALS.get(r["size"])
            if goal:
                lim = goal[1] if goal[1] is not None else 3 * r["decoded_input_bytes"]
                ok = r["seconds"] <= goal[0] and r["peak_rss_bytes"] <= lim
                note += f"; goal <= {goal[0]:g} s and <= {lim / 2**30:.2f} GiB: {'met' if ok else 'NOT met'}"
        if r["step"] == "read":
            note = f"{r['negatives_clamped']} negatives clamped ({r['removed_fraction']:.1e} of the integral)"
        cpu = f"{r['cpu_seconds']:7.2f}" if "cpu_seconds" in r else f"{'':7s}"
        print(f"{r['size']:9s} {r['step']:16s} {r['seconds']:8.2f} {cpu} {r['peak_rss_bytes'] / 2**20:13.0f} "
              f"{r['peak_rss_bytes'] / r['decoded_input_bytes']:8.2f}  {note}")
    print("load:", subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip())
    if args.out:
        from ibl_ref.atomic import write_csv

        cols = ["size", "step", "seconds", "cpu_seconds", "peak_rss_bytes", "decoded_input_bytes", "rel_int_change", "prereduce",
                "negatives_clamped", "removed_fraction"]
        write_csv(args.out, [{c: r.get(c, "") for c in cols} for r in all_rows], columns=cols)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

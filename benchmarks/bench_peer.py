"""Side-by-side benchmark of the lab's Phong convolution against the peer prefilter tool cmft: the README's table.

Usage (the full matrix, both kernels, cmft released and fixed, the synthetic scene and one real probe)::

    python benchmarks/bench_peer.py --cmft PATH/cmft --cmft PATH/cmft-fixed --probe PATH/courtyard.exr \
        [--faces 64 128 256 512] [--exponents 1 4 16 64 256 1024 4096] [--kernels numpy compiled] [--set8]
        [--native] [--repeat 3] [--timeout 150] [--markdown OUT.md] [--csv OUT.csv]

Per scene (the sky + 1e5 sun 0.0015 rad from a cube corner of :func:`ibl_ref.experiments.speed_accuracy.environment`;
with ``--probe`` also a real lat-long probe, resampled to every face size up to its native one), face size N and
exponent s (one exponent per run; ``--set8``: also the 8 exponents {1, 2, 5, 10, 20, 50, 100, 1000} at once):

* **the lab, in-process** — ``convolve(cube, [s], rtol=1e-3, kernel=K, workers=2)`` in this (warm) process, as a
  notebook user calls it: imports done, the compiled kernels loaded by a warm-up call on another map; the first call
  for the cell (and, with ``--repeat`` > 1, the median of the calls after it);
* **the lab, whole process** — ``python -m ibl_ref convolve IN.exr OUT.exr -s S --rtol 1e-3 --kernel K`` (2 workers,
  the package byte-compiled first, as ``pip install`` leaves it; the compiled kernels' cache warm), from start to exit;
* **each cmft binary** given by ``--cmft`` — one radiance filter at full resolution with 2 worker threads::

      cmft --input IN.dds --filter radiance --srcFaceSize 0 --dstFaceSize 0 --excludeBase false
           --mipCount 1 --lightingModel phong --edgeFixup none --numCpuProcessingThreads 3
           --useOpenCL false --glossScale K --glossBias 0 --generateMipChain false
           --outputNum 1 --output0 OUT --output0params dds,rgba32f,cubemap --silent

  (s = 2^K; ``--numCpuProcessingThreads 3`` starts 2 worker threads, cmft's main thread only waits).  cmft reaches
  only s = 2^K: its "8 exponents" cell is the sum of its runs at the nearest powers of two {1, 2, 4, 8, 16, 64, 128,
  1024}.  A run that exceeds ``--timeout`` seconds is killed (the ratio is then a bound).

Wall time (median of ``--repeat``) and CPU time (user + system of the process and its children; in-process: of
this process and its forked workers) are printed; CPU depends least on what else runs on a shared machine.

Error: the max relative error ``|approx − exact|/exact`` (max over RGB) of every tool's output against the exact
float64 lobe average (:func:`ibl_ref.experiments.speed_accuracy.exact_subset`, every source texel) of the same
float32-rounded input, at a seeded random subset of 1 500 output texels plus the 300 nearest the brightest texel
(where truncated supports fail); for cmft at its own exponent 2^K.  The lab's whole-process outputs are float32 files
(error floor ≈ 6e-8); its in-process maps float64.

The verdict columns: in-process — the first call ≤ cmft's whole run where that takes ≥ 50 ms (with ``--repeat`` > 1
the ratio of the median repeated call too); process — the better kernel's whole process ≤ cmft's where cmft needs
≥ 0.5 s; faster cells have no target (they are bound by start-up: :data:`IO_FLOOR`, start Python, import NumPy and
OpenEXR, read the input EXR and write one of the same size, is measured per face size in the same run).

Also measured: the start-up floor (``python -S``, ``import numpy``, ``import numpy, OpenEXR``, ``import numba``,
loading the compiled kernels from numba's cache (:mod:`ibl_ref.groundtruth.kernels`), ``ibl-ref convolve --help``);
the compiled kernels' cold (first run after install: an empty cache folder, ``$NUMBA_CACHE_DIR``, so numba compiles)
and warm whole-process cost
on one cell; the machine's compiled peak (a tight multiply-add loop and a dot product, per core) against the pairs
(output × source texel) per second per core the sparse gather computes in the in-process cells (the bright texels a
tile leaves out are not counted); with ``--native`` the 512² and 1024² runs of the 8 exponents (whole process,
peak RSS by ``/usr/bin/time -v``).  The face mapping between the two conventions is verified on a smooth pattern
first.  Output: progress lines, then markdown tables (``--markdown`` writes them to a file too) headed by the
command, the commit and the load average at start and end.  The binaries are not part of the project.
"""

from __future__ import annotations

import argparse
import math
import os
import resource
import struct
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402

from ibl_ref.environment import envmap  # noqa: E402
from ibl_ref.atomic import write_csv  # noqa: E402

S8 = (1.0, 2.0, 5.0, 10.0, 20.0, 50.0, 100.0, 1000.0)
DEFAULT_EXPONENTS = (1.0, 4.0, 16.0, 64.0, 256.0, 1024.0, 4096.0, math.inf)
RTOL = 1e-3
#: the targets (issue 39): the lab's first in-process call ≤ cmft's whole run where that takes ≥ 50 ms, the lab's whole
#: process ≤ cmft's where that takes ≥ 0.5 s; faster cells are bound by start-up and have no target
IN_PROCESS_MIN_S = 0.05
PROCESS_MIN_S = 0.5
SUBSET = 1500
NEAR_SUN = 300
SEED = 20140

# ---- DDS cube maps (legacy header, D3DFMT_A32B32G32R32F = FourCC 116) -----------------------------
_DDSD = 0x1 | 0x2 | 0x4 | 0x8 | 0x1000  # CAPS | HEIGHT | WIDTH | PITCH | PIXELFORMAT
_DDPF_FOURCC = 0x4
_CAPS = 0x8 | 0x1000  # COMPLEX | TEXTURE
_CAPS2_CUBE = 0x200 | 0xFC00  # CUBEMAP | all six faces
_FOURCC_RGBA32F = 116
_DXGI_R32G32B32A32_FLOAT = 2


def write_dds_cube(path, cube_gl) -> None:
    """Write a ``(6, N, N, 3)`` cube (faces already in the OpenGL convention) as a DDS RGBA32F cube map."""
    n = cube_gl.shape[1]
    rgba = np.ones(cube_gl.shape[:3] + (4,), dtype="<f4")
    rgba[..., :3] = cube_gl
    hdr = struct.pack("<4s7I44x", b"DDS ", 124, _DDSD, n, n, n * 16, 0, 1)
    hdr += struct.pack("<2I4s5I", 32, _DDPF_FOURCC, struct.pack("<I", _FOURCC_RGBA32F), 0, 0, 0, 0, 0)
    hdr += struct.pack("<4I4x", _CAPS, _CAPS2_CUBE, 0, 0)
    assert len(hdr) == 128
    Path(path).write_bytes(hdr + rgba.tobytes())


def read_dds_cube(path) -> np.ndarray:
    """Read a DDS RGBA32F cube map (legacy FourCC 116 or DX10 R32G32B32A32_FLOAT) as ``(6, N, N, 3)``."""
    buf = Path(path).read_bytes()
    if buf[:4] != b"DDS ":
        raise ValueError(f"{path}: not a DDS file")
    h, w = struct.unpack_from("<2I", buf, 12)
    fourcc = buf[84:88]
    off = 128
    if fourcc == b"DX10":
        fmt = struct.unpack_from("<I", buf, 128)[0]
        if fmt != _DXGI_R32G32B32A32_FLOAT:
            raise ValueError(f"{path}: DXGI format {fmt}, expected R32G32B32A32_FLOAT")
        off += 20
    elif struct.unpack("<I", fourcc)[0] != _FOURCC_RGBA32F:
        raise ValueError(f"{path}: pixel format {fourcc!r}, expected RGBA32F")
    if h != w:
        raise ValueError(f"{path}: non-square faces {w}x{h}")
    need = 6 * h * w * 16
    a = np.frombuffer(buf, dtype="<f4", count=need // 4, offset=off)
    return a.reshape(6, h, w, 4)[..., :3].astype(np.float64)


# ---- runs ----------------------------------------------------------------------------------------
def _load():
    try:
        return f"load avg {os.getloadavg()[0]:.2f} (1 min) on {os.cpu_count()} CPUs"
    except OSError:
        return "load avg n/a"


def _child_cpu():
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def _timed_run(cmd, timeout, env=None):
    """Run ``cmd``; returns ``(completed or None on timeout, wall s, CPU s of the process and its children)``."""
    t0, c0 = time.perf_counter(), _child_cpu()
    try:
        p = subprocess.run(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, timeout=timeout, env=env)
    except subprocess.TimeoutExpired:
        return None, time.perf_counter() - t0, math.nan
    dt, dc = time.perf_counter() - t0, _child_cpu() - c0
    if p.returncode != 0:
        raise RuntimeError(f"{cmd[0]} failed ({p.returncode}): {p.stderr.decode(errors='replace')[-400:]}")
    return p, dt, dc


def cmft_cmd(binary, inp, outbase, s):
    if math.isinf(s):
        return [binary, "--input", str(inp), "--filter", "none", "--outputNum", "1", "--output0", str(outbase),
                "--output0params", "dds,rgba32f,cubemap", "--silent"]
    k = math.log2(s)
    if abs(k - round(k)) > 1e-12:
        raise ValueError(f"cmft reaches only s = 2^K, not {s}")
    return [binary, "--input", str(inp), "--filter", "radiance", "--srcFaceSize", "0", "--dstFaceSize", "0",
            "--excludeBase", "false", "--mipCount", "1", "--lightingModel", "phong", "--edgeFixup", "none",
            "--numCpuProcessingThreads", "3", "--useOpenCL", "false", "--glossScale", str(int(round(k))),
            "--glossBias", "0", "--generateMipChain", "false", "--outputNum", "1", "--output0", str(outbase),
            "--output0params", "dds,rgba32f,cubemap", "--silent"]


def lab_env():
    """Environment of the lab's processes: this checkout first on the path, with byte-code caching on
    (``PYTHONDONTWRITEBYTECODE`` removed; :func:`compile_lab` writes the caches first), as in an installed
    package, whose modules pip compiles at install time.  Without the caches every run compiles the
    package's sources again (≈ 0.1 s of each whole-process run, measured on the 2-core machine)."""
    env = dict(os.environ)
    env["PYTHONPATH"] = str(ROOT) + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    env.pop("PYTHONDONTWRITEBYTECODE", None)
    return env


def compile_lab():
    """Byte-compile the package once, before any timing (what ``pip install`` does)."""
    subprocess.run([sys.executable, "-m", "compileall", "-q", str(ROOT / "ibl_ref")], check=True,
                   stdout=subprocess.DEVNULL, env=lab_env())


def nearest_pow2(s):
    return 2.0 ** round(math.log2(s))


def sample_texels(cube, n):
    """Seeded random output texels plus the ones nearest the brightest source texel (flat indices)."""
    rng = np.random.default_rng(SEED)
    tot = 6 * n * n
    idx = set(rng.choice(tot, size=min(SUBSET, tot), replace=False).tolist())
    d = envmap.texel_directions(n).reshape(-1, 3)
    sun = d[int(np.argmax(cube.max(axis=-1).ravel()))]
    idx.update(np.argsort(-(d @ sun))[: min(NEAR_SUN, tot)].tolist())
    return np.array(sorted(idx))


def rel_error(approx, ref):
    with np.errstate(divide="ignore", invalid="ignore"):
        e = np.abs(approx - ref) / ref
    return float(np.max(np.where(ref > 0, e, np.where(approx == ref, 0.0, np.inf))))


class Reference:
    """Exact float64 lobe averages of one input at a fixed set of texels, cached per exponent."""

    def __init__(self, cube):
        from ibl_ref.experiments.speed_accuracy import exact_subset

        self.cube, self.n = cube, cube.shape[1]
        self.idx = sample_texels(cube, self.n)
        self._f, self._cache = exact_subset, {}

    def at(self, s):
        if s not in self._cache:
            if math.isinf(s):
                self._cache[s] = self.cube.reshape(-1, 3)[self.idx]
            else:
                self._cache[s] = self._f(self.cube, [s], self.idx)[0]
        return self._cache[s]

    def error(self, result_cube, s):
        return rel_error(result_cube.reshape(-1, 3)[self.idx], self.at(s))


def check_face_mapping(binary, tmp):
    """cmft on a smooth pattern (16² faces, s = 64) vs the lab's exact gather: max rel. error (must be < 5 %)."""
    from ibl_ref.groundtruth.phong_convolution import convolve_exact_many

    n = 16
    d = envmap.texel_directions(n)
    pat = np.stack([1.5 + d[..., 0] + 0.3 * d[..., 1] * d[..., 2], 1.5 + d[..., 1], 1.5 + d[..., 2] - 0.2 * d[..., 0]],
                   axis=-1).astype(np.float32).astype(np.float64)
    write_dds_cube(tmp / "pattern.dds", envmap.convert_convention(pat, "openexr", "opengl"))
    _timed_run(cmft_cmd(binary, tmp / "pattern.dds", tmp / "pattern_out", 64.0), 120)
    got = envmap.convert_convention(read_dds_cube(tmp / "pattern_out.dds"), "opengl", "openexr")
    ref = convolve_exact_many(pat, [64.0])[0]
    err = rel_error(got, ref)
    # the same output read without re-orienting (what a wrong mapping would give) for contrast
    wrong = rel_error(read_dds_cube(tmp / "pattern_out.dds"), ref)
    return err, wrong


def median_wall(cmd, repeat, timeout, env=None):
    """Median wall and CPU seconds over ``repeat`` runs (``(None, ...)`` if a run timed out)."""
    walls, cpus = [], []
    for _ in range(repeat):
        p, dt, dc = _timed_run(cmd, timeout, env)
        if p is None:
            return None, [dt], math.nan
        walls.append(dt)
        cpus.append(dc)
    return float(np.median(walls)), walls, float(np.median(cpus))


#: start-up floors of a Python process: what any whole-process run of the lab costs at least
FLOOR_COMMANDS = {
    "python -S -c pass": [sys.executable, "-S", "-c", "pass"],
    "python -c 'import numpy'": [sys.executable, "-c", "import numpy"],
    "python -c 'import numpy, OpenEXR'": [sys.executable, "-c", "import numpy, OpenEXR"],
    "ibl-ref convolve --help": [sys.executable, "-m", "ibl_ref", "convolve", "--help"],
    "python -c 'import numba'": [sys.executable, "-c", "import numba"],
    "load the compiled kernels (numba's cache)": [
        sys.executable, "-c", "from ibl_ref.groundtruth.kernels import get_kernels; get_kernels('compiled').warm_up()"],
}


#: the interpreter floor of one cell: start Python, import NumPy and OpenEXR, read the input EXR and write an EXR of
#: the same size with the OpenEXR binding (what any Python tool run as a process must do; none of the lab's code)
IO_FLOOR = ("import sys, OpenEXR, numpy; f = OpenEXR.File(sys.argv[1]); "
            "OpenEXR.File(f.header(), {k: v.pixels for k, v in f.channels().items()}).write(sys.argv[2])")


def measure_io_floor(inp, out, repeat):
    """Median wall seconds of :data:`IO_FLOOR` on ``inp`` (a whole process)."""
    w, _walls, _c = median_wall([sys.executable, "-c", IO_FLOOR, str(inp), str(out)], repeat, None, lab_env())
    return w


def measure_floor(repeat):
    """Median wall and CPU seconds of :data:`FLOOR_COMMANDS` (whole processes)."""
    out = {}
    for label, cmd in FLOOR_COMMANDS.items():
        runs = []
        for _ in range(max(1, repeat)):
            try:
                _, w, c = _timed_run(cmd, None, lab_env())
            except RuntimeError:
                break  # e.g. numba not installed
            runs.append((w, c))
        if runs:
            runs.sort()
            out[label] = runs[len(runs) // 2]
    return out


def measure_peak():
    """Compiled peak of one core: multiply-adds per second of a tight loop (32 dependent multiply-adds per element,
    elements independent: compute-bound) and of a dot product in the L1 cache (2 loads per multiply-add)."""
    import numba

    @numba.njit(fastmath={"contract"})
    def madd(a, out, reps):
        for _ in range(reps):
            for j in range(a.shape[0]):
                x = a[j]
                p = 0.5
                for _k in range(32):
                    p = p * x + 0.25
                out[j] = p

    @numba.njit(fastmath={"contract", "reassoc"})
    def dot(a, b, reps):
        t = 0.0
        for _ in range(reps):
            for j in range(a.shape[0]):
                t += a[j] * b[j]
        return t

    a, o, b = np.random.default_rng(0).random(1024), np.empty(1024), np.random.default_rng(1).random(1024)
    madd(a, o, 1)
    dot(a, b, 1)
    c0 = time.process_time()
    madd(a, o, 20000)
    t_madd = time.process_time() - c0
    c0 = time.process_time()
    dot(a, b, 400000)
    t_dot = time.process_time() - c0
    return 1024 * 32 * 20000 / t_madd, 1024 * 400000 / t_dot


def lab_cmd(inp, out, exps, kernel="auto"):
    cmd = [sys.executable, "-m", "ibl_ref", "convolve", str(inp), str(out), "--rtol", str(RTOL), "--kernel", kernel]
    for s in exps:
        cmd += ["-s", "inf" if math.isinf(s) else format(s, "g")]
    return cmd


def timed_rss(cmd, env):
    """Wall, CPU and peak RSS (GiB, the largest process, ``/usr/bin/time -v``) of one whole-process run."""
    t0, c0 = time.perf_counter(), _child_cpu()
    p = subprocess.run(["/usr/bin/time", "-v"] + cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env)
    wall, cpu = time.perf_counter() - t0, _child_cpu() - c0
    if p.returncode != 0:
        raise RuntimeError(p.stderr.decode(errors="replace")[-400:])
    rss = next((float(ln.split(":")[1]) / 2**20 for ln in p.stderr.decode().splitlines()
                if "Maximum resident set size" in ln), math.nan)
    return wall, cpu, rss


def _fmt(w, c):
    return "—" if w is None else f"{w:.2f} / {c:.2f}"


def _err(e):
    return "—" if e is None else f"{e:.0e}"


def main(argv=None):
    from ibl_ref.cli.cmd_convolve import exponent_path
    from ibl_ref.environment.exr_io import load_cube, write_envmap
    from ibl_ref.experiments.speed_accuracy import environment
    from ibl_ref.groundtruth.convolve import convolve

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cmft", action="append", default=[], metavar="PATH", help="cmft binary (repeatable)")
    ap.add_argument("--faces", type=int, nargs="+", default=[64, 128, 256, 512])
    ap.add_argument("--exponents", nargs="+", default=None, help="exponents (default 1 4 16 64 256 1024 4096)")
    ap.add_argument("--kernels", nargs="+", default=["numpy", "compiled"], choices=("numpy", "compiled"))
    ap.add_argument("--probe", default=None, help="also a real lat-long probe (resampled to the face sizes ≤ native)")
    ap.add_argument("--set8", action="store_true", help="also the 8-exponent set in one lab run")
    ap.add_argument("--native", action="store_true", help="the 512² and 1024² 8-exponent runs (peak RSS)")
    ap.add_argument("--repeat", type=int, default=3, help="runs per cell (median wall time)")
    ap.add_argument("--timeout", type=float, default=150.0, help="seconds after which a cmft run is killed")
    ap.add_argument("--no-process", action="store_true", help="skip the lab's whole-process runs")
    ap.add_argument("--no-error", action="store_true", help="skip the error measurement (timing only)")
    ap.add_argument("--csv", type=Path, default=None, help="write all cells as CSV")
    ap.add_argument("--markdown", type=Path, default=None, help="write the tables to this file too")
    ap.add_argument("--save-dir", type=Path, default=None,
                    help="write the run's data in the documentation's layout (cells.csv, verdicts.csv, …, run.json) "
                         "to this folder (e.g. tests/data/readme_runs/bench-peer; then python docs/make_results.py)")
    args = ap.parse_args(argv)
    exps = [float(e) for e in args.exponents] if args.exponents else [1.0, 4.0, 16.0, 64.0, 256.0, 1024.0, 4096.0]
    cmfts = [str(Path(c).resolve()) for c in args.cmft]
    cmft_names = ["cmft fixed" if "fixed" in Path(c).name else "cmft" for c in cmfts]
    commit = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"], capture_output=True,
                            text=True).stdout.strip()
    dirty = subprocess.run(["git", "-C", str(ROOT), "status", "--porcelain", "--untracked-files=no"],
                           capture_output=True, text=True).stdout.strip()
    started = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
    load0 = _load()
    md = [f"Command: `python benchmarks/bench_peer.py {' '.join(sys.argv[1:] if argv is None else argv)}`; "
          f"commit `{commit}`{' (with uncommitted changes)' if dirty else ''}; started {started}, {load0}."]
    print(md[0], flush=True)
    compile_lab()
    env = lab_env()
    peak_madd = peak_dot = None
    if "compiled" in args.kernels:  # warm the compiled kernels here (in-process) and in the cache (processes): the
        # first use after an installation builds them (the cold cost, measured below on its own cache folder)
        convolve(environment(8), [2.0, 64.0, 4096.0], kernel="compiled")
        convolve(environment(16), [1.0, 5.0], kernel="compiled", method="auto")
        peak_madd, peak_dot = measure_peak()
    n_floor = max(3, args.repeat)
    floor = measure_floor(n_floor)
    md.append("")
    md.append("**Start-up floor** (whole processes, median of %d): " % n_floor + "; ".join(
        f"{k} {w:.2f} s wall / {c:.2f} s CPU" for k, (w, c) in floor.items()) + ".")
    print(md[-1], flush=True)
    for k in args.kernels:
        convolve(environment(8), [2.0, 64.0], kernel=k)
    rows, native, cold = [], [], []
    scenes = [("sky + sun", None)] + ([(Path(args.probe).stem, args.probe)] if args.probe else [])
    with tempfile.TemporaryDirectory(prefix="bench_peer_") as td:
        tmp = Path(td)
        if cmfts:
            err, wrong = check_face_mapping(cmfts[0], tmp)
            md.append(f"Face mapping check (16², s = 64, smooth pattern): cmft vs the lab's exact gather {err:.1e} "
                      f"(without re-orienting the faces: {wrong:.1e}).")
            print(md[-1], flush=True)
            if not err < 0.05:
                raise SystemExit("face mapping check failed: cmft output does not match the lab's convention")
        if "compiled" in args.kernels and not args.no_process:  # cold (empty numba cache) and warm, one cell
            cube = environment(64).astype(np.float32).astype(np.float64)
            write_envmap(tmp / "cold.exr", cube, layout="cube")
            e2 = dict(env, NUMBA_CACHE_DIR=str(tmp / "numba_cache"))
            cold = [_timed_run(lab_cmd(tmp / "cold.exr", tmp / "cold_out.exr", [1.0, 5.0, 1000.0], "compiled"), None,
                               e2)[1:] for _ in range(3)]
            md.append("**Compile cost** (64², s = 1, 5, 1000 in one run, `--kernel compiled`, an empty numba cache "
                      f"first): cold {cold[0][0]:.1f} s wall / {cold[0][1]:.1f} s CPU; warm {cold[1][0]:.2f} / "
                      f"{cold[1][1]:.2f} s and {cold[2][0]:.2f} / {cold[2][1]:.2f} s.")
            print(md[-1], flush=True)
        for scene, path in scenes:
            native_size = None  # (not `native`: that list collects the --native runs)
            if path:
                native_size = load_cube(path).shape[1]
            for n in args.faces:
                if native_size is not None and n > native_size:
                    continue
                cube = (environment(n) if path is None else load_cube(path, size=n)).astype(np.float32).astype(
                    np.float64)
                inp_exr, inp_dds = tmp / f"in{n}.exr", tmp / f"in{n}.dds"
                write_envmap(inp_exr, cube, layout="cube")
                write_dds_cube(inp_dds, envmap.convert_convention(cube, "openexr", "opengl"))
                io_floor = measure_io_floor(inp_exr, tmp / "io_floor.exr", max(3, args.repeat))
                ref = None if args.no_error else Reference(cube)
                cells = [("s", (s,)) for s in exps] + ([("set8", S8)] if args.set8 else [])
                for kind, ss in cells:
                    label = "8 exponents" if kind == "set8" else format(ss[0], "g")
                    row = {"scene": scene, "face": n, "s": label, "io_floor_wall_s": io_floor}
                    for k in args.kernels:
                        runs = []
                        for _ in range(max(1, args.repeat)):
                            t0 = time.perf_counter()
                            r = convolve(cube, list(ss), rtol=RTOL, kernel=k, workers=2)
                            runs.append((time.perf_counter() - t0, r.timings_s["total_cpu"]))
                        row[f"{k}_inproc_first_wall_s"], row[f"{k}_inproc_first_cpu_s"] = runs[0]
                        rep = runs[1:] or runs  # the repeated calls (the first one pays the per-cell set-up)
                        row[f"{k}_inproc_wall_s"] = float(np.median([w for w, _ in rep]))
                        row[f"{k}_inproc_cpu_s"] = float(np.median([c for _, c in rep]))
                        row[f"{k}_routes"] = ",".join(sorted(set(r.method_used.values())))
                        row[f"{k}_bound"] = max(float(np.max(r.error_bound[s])) for s in ss)
                        if r.info.get("sparse_pairs") and r.timings_s.get("sparse"):
                            row[f"{k}_sparse_pairs_per_core_s"] = r.info["sparse_pairs"] / r.timings_s["sparse"]
                        if ref is not None:
                            row[f"{k}_err"] = max(ref.error(r.maps[s], s) for s in ss)
                        if not args.no_process:
                            out = tmp / f"lab{n}.exr"
                            w, walls, c = median_wall(lab_cmd(inp_exr, out, ss, k), args.repeat, None, env)
                            row[f"{k}_proc_wall_s"], row[f"{k}_proc_cpu_s"] = w, c
                            if ref is not None:
                                row[f"{k}_proc_err"] = max(ref.error(load_cube(exponent_path(out, s)), s) for s in ss)
                    for name, c in zip(cmft_names, cmfts):
                        tot, tot_cpu, err_c, timed_out = 0.0, 0.0, 0.0, False
                        for s_c in dict.fromkeys(nearest_pow2(s) for s in ss):
                            w_c, _, c_c = median_wall(cmft_cmd(c, inp_dds, tmp / "cm", s_c), args.repeat, args.timeout)
                            if w_c is None:
                                timed_out = True
                                break
                            tot += w_c
                            tot_cpu += c_c
                            if ref is not None:
                                got = envmap.convert_convention(read_dds_cube(tmp / "cm.dds"), "opengl", "openexr")
                                err_c = max(err_c, ref.error(got, s_c))
                        row[f"{name}_wall_s"] = None if timed_out else tot
                        row[f"{name}_cpu_s"] = None if timed_out else tot_cpu
                        row[f"{name}_err"] = None if (timed_out or ref is None) else err_c
                    rows.append(row)
                    print("  " + ", ".join(f"{a}={b:.3g}" if isinstance(b, float) else f"{a}={b}"
                                           for a, b in row.items()) + f" [{_load()}]", flush=True)
        if args.native:
            md.append("")
            md.append("**Native resolution, 8 exponents** {1, 2, 5, 10, 20, 50, 100, 1000} (sky + sun, float32 cube "
                      "EXR, 2 workers, whole process):")
            md.append("")
            md.append("| face | kernel | wall s | CPU s | peak RSS (largest process) GiB | routes | largest bound |")
            md.append("|---|---|---|---|---|---|---|")
            for n in (512, 1024):
                cube = environment(n).astype(np.float32).astype(np.float64)
                write_envmap(tmp / f"nat{n}.exr", cube, layout="cube")
                del cube
                for k in args.kernels:
                    w, c, rss = timed_rss(lab_cmd(tmp / f"nat{n}.exr", tmp / f"nat{n}_o.exr", S8, k), env)
                    import json

                    side = json.loads((tmp / f"nat{n}_o.json").read_text())
                    meth = ", ".join(f"{e['s']:g}:{e['method']}" for e in side["exponents"])
                    b = max(e["rel_bound_max"] or math.inf for e in side["exponents"])
                    md.append(f"| {n}² | {k} | {w:.1f} | {c:.1f} | {rss:.2f} | {meth} | {b:.1e} |")
                    native.append({"face_size_texels": n, "kernel": k, "wall_s": f"{w:.1f}", "cpu_s": f"{c:.1f}",
                                   "peak_rss_largest_process_GiB": f"{rss:.2f}", "routes": meth,
                                   "largest_bound": f"{b:.1e}"})
                    print(md[-1] + f" [{_load()}]", flush=True)
    load1 = _load()
    # ---- tables ----
    best_k = "compiled" if "compiled" in args.kernels else args.kernels[0]
    for scene, _p in scenes:
        md.append("")
        md.append(f"**{scene}** — wall / CPU seconds; in-process = the first call in a warm process; process = "
                  "`ibl-ref convolve` from start to exit; err = max relative error against the exact float64 gather.")
        md.append("")
        head = ["face", "s"]
        for k in args.kernels:
            head += [f"lab {k} in-process", f"lab {k} process", f"lab {k} err"]
        for name in cmft_names:
            head += [f"{name}", f"{name} err"]
        if cmft_names:
            head += [f"in-process ({best_k}) ≤ {cmft_names[0]}", f"process (better kernel) ≤ {cmft_names[0]}"]
        md.append("| " + " | ".join(head) + " |")
        md.append("|" + "---|" * len(head))
        for row in (r for r in rows if r["scene"] == scene):
            cells = [f"{row['face']}²", row["s"]]
            for k in args.kernels:
                cells += [_fmt(row.get(f"{k}_inproc_first_wall_s"), row.get(f"{k}_inproc_first_cpu_s")),
                          _fmt(row.get(f"{k}_proc_wall_s"), row.get(f"{k}_proc_cpu_s")),
                          _err(max((row[x] for x in (f"{k}_err", f"{k}_proc_err") if row.get(x) is not None),
                                   default=None))]
            for name in cmft_names:
                w = row.get(f"{name}_wall_s")
                cells += [f"> {args.timeout:.0f} (killed)" if w is None else _fmt(w, row[f"{name}_cpu_s"]),
                          _err(row.get(f"{name}_err"))]
            if cmft_names:
                w_c = row.get(f"{cmft_names[0]}_wall_s")
                lab_in = row.get(f"{best_k}_inproc_first_wall_s")
                procs = [row[f"{k}_proc_wall_s"] for k in args.kernels if row.get(f"{k}_proc_wall_s") is not None]
                lab_p = min(procs) if procs else None  # the better kernel: what --kernel auto aims at
                fl = row["io_floor_wall_s"]
                if w_c is None:
                    cells += ["yes (cmft killed)", "yes (cmft killed)" if lab_p is not None else "—"]
                    row["verdicts"] = cells[-2:]
                else:
                    # the targets: in-process where cmft's whole run takes ≥ IN_PROCESS_MIN_S, whole process where
                    # it takes ≥ PROCESS_MIN_S (faster cells are start-up bound: no target, the ratio shown)
                    rep = row.get(f"{best_k}_inproc_wall_s")
                    ratio = (f"{lab_in / w_c:.2f}×" + (f"; repeated call {rep / w_c:.2f}×" if args.repeat > 1 and rep
                                                       else ""))
                    cells.append(f"{'yes' if lab_in <= w_c else 'no'} ({ratio})" if w_c >= IN_PROCESS_MIN_S
                                 else f"no target ({ratio})")
                    if lab_p is None:
                        cells.append("—")
                    else:
                        cells.append(f"{'yes' if lab_p <= w_c else 'no'} ({lab_p / w_c:.2f}×)" if w_c >= PROCESS_MIN_S
                                     else f"no target ({lab_p:.2f} s vs {w_c:.2f} s)")
                    row["verdicts"] = cells[-2:]
            md.append("| " + " | ".join(cells) + " |")
    if rows:
        md.append("")
        fl = {}
        for r in rows:
            fl.setdefault((r["scene"], r["face"]), r["io_floor_wall_s"])
        md.append("**Interpreter floor of a cell** (a process that starts Python, imports NumPy and OpenEXR, reads the "
                  "input EXR and writes an EXR of the same size with the OpenEXR binding; median wall seconds; what "
                  "any Python process costs at least, which is why cells where cmft takes < 0.5 s have no process "
                  "target): " + "; ".join(
                      f"{sc} {f}² {w:.2f} s" for (sc, f), w in fl.items()) + ".")
    if "compiled" in args.kernels:
        md.append("")
        pps = [(r["scene"], r["face"], r["s"], k, r[f"{k}_sparse_pairs_per_core_s"]) for r in rows
               for k in args.kernels if r.get(f"{k}_sparse_pairs_per_core_s")]
        md.append(f"**Machine peak** (one core, compiled): {peak_madd / 1e9:.1f} G multiply-adds/s (tight loop), "
                  f"{peak_dot / 1e9:.1f} G/s (dot product in L1).  Sparse gather, (output × source texel) pairs per "
                  "second per core (pairs / summed job seconds), in-process cells: " + "; ".join(
                      f"{sc} {f}² s={s} {k} {v / 1e9:.2f} G" for sc, f, s, k, v in pps) + ".")
    md.append("")
    md.append(f"Ended {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, {load1} (started at {load0}).")
    text = "\n".join(md)
    print()
    print(text)
    if args.markdown:
        args.markdown.write_text(text + "\n")
    if args.csv and rows:
        keys = list(dict.fromkeys(k for r in rows for k in r if k != "verdicts"))
        write_csv(args.csv, [{k: v for k, v in r.items() if k != "verdicts"} for r in rows], keys)
        print(f"wrote {args.csv}")
    if args.save_dir:
        save_run(args.save_dir, md[0], started, load0, load1, args, cmft_names, rows, floor, cold, native,
                 (peak_madd, peak_dot))
    return rows


def _f2(x):
    return None if x is None else f"{x:.2f}"


def save_run(folder: Path, head, started, load0, load1, args, cmft_names, rows, floor, cold, native, peak):
    """The run's data in the documentation's layout (``docs/make_results.py``'s bench-peer page): one row per cell
    and tool in ``cells.csv``, the verdicts as printed, the floors, compile cost, machine peak, pairs per second, the
    native runs, and ``run.json`` with the command, commit, date and load."""
    import json

    from ibl_ref.atomic import atomic_write

    folder.mkdir(parents=True, exist_ok=True)
    note = f"bench_peer.py run started {started}"
    cells, verdicts, pps = [], [], []
    for r in rows:
        key = {"scene": r["scene"], "face_size_texels": r["face"], "exponents": "set8" if r["s"] == "8 exponents"
               else r["s"]}
        for k in args.kernels:
            err = max((r[x] for x in (f"{k}_err", f"{k}_proc_err") if r.get(x) is not None), default=None)
            cells.append({**key, "tool": f"lab {k}", "mode": "in-process", "wall_s": _f2(r[f"{k}_inproc_first_wall_s"]),
                          "cpu_s": _f2(r[f"{k}_inproc_first_cpu_s"]), "max_rel_err": _err(err), "status": "ok"})
            cells.append({**key, "tool": f"lab {k}", "mode": "process", "wall_s": _f2(r.get(f"{k}_proc_wall_s")),
                          "cpu_s": _f2(r.get(f"{k}_proc_cpu_s")), "max_rel_err": _err(err), "status": "ok"})
            if r.get(f"{k}_sparse_pairs_per_core_s"):
                pps.append({**key, "kernel": k, "giga_pairs_per_s_per_core": _f2(r[f"{k}_sparse_pairs_per_core_s"] / 1e9)})
        for name in cmft_names:
            w = r.get(f"{name}_wall_s")
            cells.append({**key, "tool": name, "mode": "process", "wall_s": _f2(w), "cpu_s": _f2(r.get(f"{name}_cpu_s")),
                          "max_rel_err": _err(r.get(f"{name}_err")) if w is not None else None,
                          "status": "ok" if w is not None else "killed"})
        if "verdicts" in r:
            verdicts.append({**key, "in_process_compiled_le_cmft": r["verdicts"][0],
                             "process_better_kernel_le_cmft": r["verdicts"][1]})
    tables = {
        "cells.csv": cells, "verdicts.csv": verdicts, "native_8_exponents.csv": native,
        "startup_floor.csv": [{"what": k, "wall_s": _f2(w), "cpu_s": _f2(c)} for k, (w, c) in floor.items()],
        "compile_cost.csv": [{"run": name, "wall_s": f"{w:.2f}", "cpu_s": f"{c:.2f}"}
                             for name, (w, c) in zip(("cold", "warm 1", "warm 2"), cold)],
        "interpreter_floor.csv": list({(r["scene"], r["face"]): {"scene": r["scene"], "face_size_texels": r["face"],
                                                                 "wall_s": _f2(r["io_floor_wall_s"])}
                                       for r in rows}.values()),
        "machine_peak.csv": ([{"what": "multiply-adds, tight loop", "giga_per_s": f"{peak[0] / 1e9:.1f}"},
                              {"what": "multiply-adds, dot product in L1", "giga_per_s": f"{peak[1] / 1e9:.1f}"}]
                             if peak[0] else []),
        "pairs_per_second.csv": pps,
    }
    files = []
    for name, table in tables.items():
        if table:
            write_csv(folder / name, table, list(table[0]), comment=f"{name[:-4]} of the {note}")
            files.append(name)
    meta = {"title": "Convolution against the peer tool cmft", "runs": [{
        "files": files, "what": "one run of bench_peer.py", "command": head.split("`")[1],
        "commit": head.split("`")[3], "date": started, "load": f"{load0} at the start, {load1} at the end"}]}
    with atomic_write(folder / "run.json") as fh:
        json.dump(meta, fh, indent=1, ensure_ascii=False)
        fh.write("\n")
    print(f"wrote {folder}")


if __name__ == "__main__":
    main()

"""Side-by-side benchmark of ``ibl-ref convolve`` against the peer prefilter tool cmft (whole processes).

Usage::

    python benchmarks/bench_peer.py [--cmft PATH [--cmft PATH ...]] [--faces 32 64 128]
        [--exponents 1 4 16 64 256 1024 4096 inf] [--set8] [--repeat 3] [--timeout 120]
        [--csv OUT.csv]

What it runs, per cell (face size N, exponent s):

* **the lab** — ``python -m ibl_ref convolve IN.exr OUT.exr -s S --rtol 1e-3`` (method ``auto``, default
  workers) as a separate process, timed from start to exit (start-up, file reading and writing
  included), with the package byte-compiled first, as ``pip install`` leaves it;
* **each cmft binary** given by ``--cmft`` — one radiance filter at full resolution::

      cmft --input IN.dds --filter radiance --srcFaceSize 0 --dstFaceSize 0 --excludeBase false
           --mipCount 1 --lightingModel phong --edgeFixup none --numCpuProcessingThreads 3
           --useOpenCL false --glossScale K --glossBias 0 --generateMipChain false
           --outputNum 1 --output0 OUT --output0params dds,rgba32f,cubemap --silent

  which filters with ``s = 2^K`` (cmft's Phong exponent is ``2^(glossScale·gloss + glossBias)`` and
  ``gloss = 1`` for a single level).  ``--numCpuProcessingThreads 3`` starts 2 worker threads (cmft's main
  thread only waits), the same 2 cores the lab uses.  The mirror ``s = ∞`` is timed against
  ``--filter none`` (a copy: the least cmft can do).

Wall time is the median of ``--repeat`` runs of the whole process; CPU time (user + system of the process
and its children, i.e. the lab's forked workers and cmft's threads) is printed too, as the measure that
depends least on what else runs on a shared machine.  A cmft run that exceeds ``--timeout``
seconds is killed and reported as ``> timeout`` (the ratio is then a lower bound).

**cmft reaches only s = 2^K.**  For the 8-exponent set {1, 2, 5, 10, 20, 50, 100, 1000} (``--set8``) the
lab runs all eight exponents in one process, while cmft is timed over the nearest powers of two in
log₂ ({1, 2, 4, 8, 16, 64, 128, 1024}), one process each, summed.

Input.  The synthetic sky + 1e5 sun 0.0015 rad from a cube corner (on three edges)
(:func:`ibl_ref.experiments.speed_accuracy.environment`), rounded to float32 once; the lab reads it as an
OpenEXR cube (float32), cmft as a DDS RGBA32F cube map written here after re-orienting the faces to the
OpenGL/D3D convention (:func:`ibl_ref.environment.envmap.convert_convention`).  cmft's DDS output is read back
(128-byte header, optional 20-byte DX10 header, then RGBA32F faces +X −X +Y −Y +Z −Z) and re-oriented to
the lab's convention.  The face mapping is verified before any timing: a smooth test pattern filtered by
the first cmft binary at s = 64 on 16² faces must agree with the lab's exact gather to 5 % (a wrong
orientation of any face gives O(1) differences; cmft's own truncation error is below that there).

Error.  Max relative error ``|approx − exact|/exact`` (max over RGB) against the lab's exact float64 lobe
average (:func:`ibl_ref.experiments.speed_accuracy.exact_subset`, every source texel) of the same
float32 input, at a seeded random subset of output texels plus the texels nearest the sun (where
truncated supports fail); for cmft at s = 2^K the reference is evaluated at cmft's own exponent.  The
mirror's exact reference is the input itself (output face size = input face size).

Prints one line per cell and a table (wall, error, ratio cmft/lab: > 1 means the lab is faster) and
writes it to ``--csv``.  Without ``--cmft`` only the lab's side is run.  Quote the load average printed
at the start and end with the numbers.  The binaries are not part of the project.
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


def lab_cmd(inp, out, exps):
    cmd = [sys.executable, "-m", "ibl_ref", "convolve", str(inp), str(out), "--rtol", str(RTOL)]
    for s in exps:
        cmd += ["-s", "inf" if math.isinf(s) else format(s, "g")]
    return cmd


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
}


def measure_floor(repeat):
    """Median wall and CPU seconds of :data:`FLOOR_COMMANDS` (whole processes)."""
    out = {}
    for label, cmd in FLOOR_COMMANDS.items():
        runs = []
        for _ in range(max(1, repeat)):
            _, w, c = _timed_run(cmd, None, lab_env())
            runs.append((w, c))
        runs.sort()
        out[label] = runs[len(runs) // 2]
    return out


def main(argv=None):
    from ibl_ref.environment.exr_io import load_cube, write_envmap
    from ibl_ref.experiments.speed_accuracy import environment

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cmft", action="append", default=[], metavar="PATH", help="cmft binary (repeatable)")
    ap.add_argument("--faces", type=int, nargs="+", default=[32, 64, 128])
    ap.add_argument("--exponents", nargs="+", default=None, help="exponents (default 1 4 16 … 4096 inf)")
    ap.add_argument("--set8", action="store_true", help="also the 8-exponent set in one lab process")
    ap.add_argument("--only-set8", action="store_true", help="only the 8-exponent set")
    ap.add_argument("--repeat", type=int, default=3, help="runs per cell (median wall time)")
    ap.add_argument("--timeout", type=float, default=120.0, help="seconds after which a cmft run is killed")
    ap.add_argument("--no-error", action="store_true", help="skip the error measurement (timing only)")
    ap.add_argument("--csv", type=Path, default=None, help="write the table as CSV")
    args = ap.parse_args(argv)
    exps = ([float(e) for e in args.exponents] if args.exponents else list(DEFAULT_EXPONENTS))
    if args.only_set8:
        exps = []
    cmfts = [str(Path(c).resolve()) for c in args.cmft]
    print(f"ibl_ref from {ROOT}; {_load()}; cmft: {', '.join(cmfts) or 'none (lab side only)'}")
    compile_lab()
    floor = measure_floor(args.repeat)
    for label, (w, c) in floor.items():
        print(f"floor {label:>34s}: {w:.3f} s wall, {c:.3f} s CPU (median of {args.repeat})")
    rows = []
    with tempfile.TemporaryDirectory(prefix="bench_peer_") as td:
        tmp = Path(td)
        if cmfts:
            err, wrong = check_face_mapping(cmfts[0], tmp)
            print(f"face mapping check (16², s = 64, smooth pattern): max rel. error {err:.2e} "
                  f"(without re-orienting the faces: {wrong:.2e})")
            if not err < 0.05:
                raise SystemExit("face mapping check failed: cmft output does not match the lab's convention")
        env = lab_env()
        for n in args.faces:
            cube = environment(n).astype(np.float32).astype(np.float64)
            inp_exr, inp_dds = tmp / f"in{n}.exr", tmp / f"in{n}.dds"
            write_envmap(inp_exr, cube, layout="cube")
            write_dds_cube(inp_dds, envmap.convert_convention(cube, "openexr", "opengl"))
            ref = None if args.no_error else Reference(cube)
            cells = [("s", (s,)) for s in exps] + ([("set8", S8)] if args.set8 or args.only_set8 else [])
            for kind, ss in cells:
                label = "8 exponents" if kind == "set8" else ("inf" if math.isinf(ss[0]) else format(ss[0], "g"))
                out = tmp / f"lab{n}.exr"
                wall, walls, cpu = median_wall(lab_cmd(inp_exr, out, ss), args.repeat, None, env)
                from ibl_ref.cli.cmd_convolve import exponent_path

                lab_err = None
                if ref is not None:
                    lab_err = max(ref.error(load_cube(exponent_path(out, s)), s) for s in ss)
                row = {"face": n, "s": label, "lab_wall_s": wall, "lab_cpu_s": cpu, "lab_max_rel_error": lab_err}
                for ci, c in enumerate(cmfts):
                    tag = f"cmft{ci}"
                    ss_c = [s if math.isinf(s) else nearest_pow2(s) for s in ss]
                    tot, tot_cpu, err_c, timed_out = 0.0, 0.0, 0.0, False
                    for s_c in dict.fromkeys(ss_c):
                        w_c, _, c_c = median_wall(cmft_cmd(c, inp_dds, tmp / "cm", s_c), args.repeat, args.timeout)
                        if w_c is None:
                            timed_out = True
                            break
                        tot += w_c
                        tot_cpu += c_c
                        if ref is not None:
                            got = envmap.convert_convention(read_dds_cube(tmp / "cm.dds"), "opengl", "openexr")
                            err_c = max(err_c, ref.error(got, s_c))
                    row[f"{tag}_wall_s"] = None if timed_out else tot
                    row[f"{tag}_cpu_s"] = None if timed_out else tot_cpu
                    row[f"{tag}_timed_out_after_s"] = args.timeout if timed_out else None
                    row[f"{tag}_max_rel_error"] = None if (timed_out or ref is None) else err_c
                    row[f"{tag}_over_lab"] = (args.timeout / wall if timed_out else tot / wall)
                    row[f"{tag}_cpu_over_lab"] = None if timed_out else tot_cpu / cpu
                rows.append(row)
                msg = (f"{n:5d}² s={label:>11s}: lab {wall:7.2f} s (runs {', '.join(f'{w:.2f}' for w in walls)}; "
                       f"CPU {cpu:.2f} s)")
                if lab_err is not None:
                    msg += f" err {lab_err:.1e}"
                for ci in range(len(cmfts)):
                    t = row[f"cmft{ci}_wall_s"]
                    tt = f"> {args.timeout:.0f} s" if t is None else f"{t:.2f} s"
                    e = row[f"cmft{ci}_max_rel_error"]
                    cr = row[f"cmft{ci}_cpu_over_lab"]
                    msg += (f" | cmft{ci} {tt}" + (f" err {e:.1e}" if e is not None else "")
                            + f" ratio {'≥ ' if t is None else ''}{row[f'cmft{ci}_over_lab']:.2f}"
                            + (f" (CPU {row[f'cmft{ci}_cpu_s']:.2f} s, ratio {cr:.2f})" if cr is not None else ""))
                print(msg, flush=True)
    print(_load())
    if args.csv and rows:
        keys = list(dict.fromkeys(k for r in rows for k in r))
        write_csv(args.csv, rows, keys)
        print(f"wrote {args.csv}")
    return rows


if __name__ == "__main__":
    main()

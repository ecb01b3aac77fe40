"""Generators of bad (and tricky-but-valid) input files for the adversarial suite.

Every file is made here from scratch: OpenEXR files through the OpenEXR binding (not through ibl_ref's
writers, which refuse NaN/negative data) or by patching the bytes of a valid file according to the
OpenEXR file layout (magic, version flags, ``name\\0type\\0size value`` attributes); Radiance files
byte by byte from the format description (``#?RADIANCE`` header, empty line, resolution line, RGBE
pixels, flat / new RLE / old RLE scanlines).  Sizes are tiny so the whole suite runs in seconds.
"""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np

N = 4  # cube face size of the valid test maps


def good_cube(seed: int = 0, n: int = N) -> np.ndarray:
    return np.random.default_rng(seed).random((6, n, n, 3)) + 0.1


def _exr_raw(path: Path, channels: dict, **header):
    import OpenEXR as ox

    h = {"compression": ox.ZIP_COMPRESSION, "type": ox.scanlineimage}
    h.update(header)
    ox.File(h, {k: np.ascontiguousarray(v) for k, v in channels.items()}).write(str(path))
    return path


def _strip(cube):
    n = cube.shape[1]
    return cube.reshape(6 * n, n, cube.shape[3]).astype(np.float32)


def _rgb(strip):
    return {"R": strip[..., 0], "G": strip[..., 1], "B": strip[..., 2]}


def write_good_exr(path: Path, seed: int = 0) -> Path:
    from ibl_ref.environment.exr_io import write_envmap

    write_envmap(path, good_cube(seed), layout="cube")
    return path


def _patch_attr(buf: bytes, name: bytes, typ: bytes, value: bytes) -> bytes:
    key = name + b"\0" + typ + b"\0"
    i = buf.index(key) + len(key)
    size = struct.unpack_from("<i", buf, i)[0]
    assert size == len(value)
    return buf[: i + 4] + value + buf[i + 4 + size :]


# ------------------------------------------------------------------------------------------------
# OpenEXR: bad files (name -> (maker(dir) -> path, expected message fragment))
# ------------------------------------------------------------------------------------------------
def _truncated(frac, nbytes=None):
    def make(d: Path):
        good = write_good_exr(d / "good_for_trunc.exr").read_bytes()
        n = nbytes if nbytes is not None else max(1, int(len(good) * frac)) if frac < 1 else len(good) - 1
        p = d / f"trunc_{n}.exr"
        p.write_bytes(good[:n])
        return p

    return make


def _bytes_file(name, data):
    def make(d: Path):
        p = d / name
        p.write_bytes(data)
        return p

    return make


def _deep(d: Path):
    import OpenEXR as ox

    px = np.empty((6 * N, N), dtype=object)
    for i in np.ndindex(px.shape):
        px[i] = np.array([1.0, 2.0], np.float32)
    p = d / "deep.exr"
    ox.File({"compression": ox.NO_COMPRESSION, "type": ox.deepscanline}, {"R": px, "G": px, "B": px}).write(str(p))
    return p


def _data_window(box, name):
    def make(d: Path):
        good = write_good_exr(d / f"good_for_{name}").read_bytes()
        p = d / name
        p.write_bytes(_patch_attr(good, b"dataWindow", b"box2i", struct.pack("<4i", *box)))
        return p

    return make


def _convention(value, name):
    def make(d: Path):
        return _exr_raw(d / name, _rgb(_strip(good_cube())), iblref_convention=value)

    return make


def _bad_values(kind):
    def make(d: Path):
        s = _strip(good_cube())
        s[3, 1, 1] = {"nan": np.nan, "inf": np.inf, "neg": -1.0}[kind]
        return _exr_raw(d / f"{kind}.exr", _rgb(s))

    return make


def _channels_z(d: Path):
    s = _strip(good_cube())
    return _exr_raw(d / "zonly.exr", {"Z": s[..., 0]})


def _aspect(d: Path):
    s = np.ones((7, 5, 3), np.float32)
    return _exr_raw(d / "aspect57.exr", _rgb(s))


def _mixed_sizes_version(d: Path):  # version field 3: unsupported
    good = bytearray(write_good_exr(d / "good_for_v3.exr").read_bytes())
    good[4] = 3
    p = d / "version3.exr"
    p.write_bytes(bytes(good))
    return p


def _corrupt_attr_size(d: Path):  # first attribute claims 2**30 bytes
    good = bytearray(write_good_exr(d / "good_for_attr.exr").read_bytes())
    i = good.index(b"chlist\0") + len(b"chlist\0")
    good[i : i + 4] = struct.pack("<i", 2**30)
    p = d / "attrsize.exr"
    p.write_bytes(bytes(good))
    return p


def _zeroed_chunks(d: Path):  # header intact, offset table and pixel chunks zeroed
    good = bytearray(write_good_exr(d / "good_for_zero.exr").read_bytes())
    end = good.index(b"\0\0", good.index(b"iblref_convention")) + 2
    for i in range(end + 8, len(good)):
        good[i] = 0
    p = d / "zeroed.exr"
    p.write_bytes(bytes(good))
    return p


def _bad_type_name(d: Path):  # the envmap attribute's type name made invalid UTF-8 (found by fuzzing)
    good = write_good_exr(d / "good_for_typename.exr").read_bytes()
    p = d / "typename.exr"
    p.write_bytes(good.replace(b"envmap\0envmap\0", b"envmap\0\xcdnvmap\0", 1))
    return p


BAD_EXR = {
    "trunc_8B": (_truncated(0, 8), "truncated"),
    "trunc_40B": (_truncated(0, 40), "OpenEXR header"),
    "trunc_header": (_truncated(0.05), "OpenEXR"),
    "trunc_half": (_truncated(0.5), "truncated"),
    "trunc_last_byte": (_truncated(1.0), "truncated"),
    "empty": (_bytes_file("empty.exr", b""), "not an OpenEXR file"),
    "bad_magic": (_bytes_file("png_named.exr", b"\x89PNG\r\n\x1a\n" + b"\0" * 64), "not an OpenEXR file"),
    "text": (_bytes_file("text.exr", b"hello world\n" * 10), "not an OpenEXR file"),
    "magic_only": (_bytes_file("magic_only.exr", b"\x76\x2f\x31\x01"), "truncated"),
    "deep": (_deep, "deep OpenEXR"),
    "huge_window": (_data_window((0, 0, 2**30, 2**30), "huge_window.exr"), "more than this machine's memory"),
    "inverted_window": (_data_window((0, 0, -5, -5), "inverted_window.exr"), "invalid OpenEXR data window"),
    "conv_directx": (_convention("directx", "conv_directx.exr"), "iblref_convention"),
    "conv_int": (_convention(7, "conv_int.exr"), "iblref_convention"),
    "nan_pixel": (_bad_values("nan"), "NaN"),
    "inf_pixel": (_bad_values("inf"), "Inf"),
    "negative_pixel": (_bad_values("neg"), "negative"),
    "z_channel_only": (_channels_z, "R/G/B"),
    "aspect_5x7": (_aspect, "layout"),
    "version3": (_mixed_sizes_version, "version"),
    "attr_size": (_corrupt_attr_size, "OpenEXR header"),
    "zeroed_chunks": (_zeroed_chunks, "OpenEXR"),
    "bad_attribute_type_name": (_bad_type_name, "corrupt OpenEXR header attribute"),
}


# ------------------------------------------------------------------------------------------------
# OpenEXR: unusual but valid files (name -> maker(dir) -> (path, expected cube))
# ------------------------------------------------------------------------------------------------
def tiled_exr(d: Path):
    import OpenEXR as ox

    cube = good_cube(3)
    td = ox.TileDescription()
    td.xSize, td.ySize, td.mode = 2, 2, ox.LevelMode.ONE_LEVEL
    p = _exr_raw(d / "tiled.exr", _rgb(_strip(cube)), type=ox.tiledimage, tiles=td, envmap=ox.ENVMAP_CUBE)
    return p, _strip(cube).astype(np.float64).reshape(cube.shape)


def multipart_exr(d: Path):
    from ibl_ref.environment.exr_io import write_pyramid

    l0, l1 = good_cube(4), good_cube(5, 2)
    p = d / "multipart.exr"
    write_pyramid(p, [l0, l1])
    return p, l0.astype(np.float32).astype(np.float64)


def opengl_exr(d: Path):
    from ibl_ref.environment.exr_io import write_envmap

    cube = good_cube(6)
    p = d / "opengl.exr"
    write_envmap(p, cube, convention="opengl")
    return p, cube.astype(np.float32).astype(np.float64)


VALID_EXR = {"tiled": tiled_exr, "multipart": multipart_exr, "opengl": opengl_exr}


# ------------------------------------------------------------------------------------------------
# Radiance .hdr
# ------------------------------------------------------------------------------------------------
HEAD = b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n"


def _flat_pixels(h, w):
    px = np.zeros((h, w, 4), np.uint8)
    px[..., :3] = 128
    px[..., 3] = 129
    return px.tobytes()


def _rle_line(w, counts=None):
    """One new-style RLE scanline: 4 components, each one run of w bytes (w <= 127)."""
    out = bytes([2, 2, w >> 8, w & 255])
    for c in range(4):
        out += bytes([128 + w, 129 if c == 3 else 128]) if counts is None else counts
    return out


H, W = 4, 8  # a 2:1 lat-long map

BAD_HDR = {
    "no_signature": (b"P6\n4 8\n255\n" + _flat_pixels(H, W), "not a Radiance HDR file"),
    "no_end_of_header": (b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n", "truncated Radiance header"),
    "no_resolution": (HEAD, "no resolution line"),
    "res_same_axis": (HEAD + b"-Y 4 -Y 8\n" + _flat_pixels(H, W), "bad resolution line"),
    "res_z_axis": (HEAD + b"-Z 4 +X 8\n" + _flat_pixels(H, W), "bad resolution line"),
    "res_words": (HEAD + b"-Y four +X eight\n" + _flat_pixels(H, W), "bad resolution line"),
    "res_zero": (HEAD + b"-Y 0 +X 8\n", "empty image"),
    "huge_claim_1e9x2e9": (HEAD + b"-Y 1000000000 +X 2000000000\n", "header claims"),
    "huge_claim_with_data": (HEAD + b"-Y 200000 +X 400000\n" + b"\x02\x02\x00\x00" * 200000,
                             "more than this machine's memory"),
    "xyze": (b"#?RADIANCE\nFORMAT=32-bit_rle_xyze\n\n-Y 4 +X 8\n" + _flat_pixels(H, W), "unsupported pixel format"),
    "bad_exposure": (b"#?RADIANCE\nEXPOSURE=bright\n\n-Y 4 +X 8\n" + _flat_pixels(H, W), "bad EXPOSURE"),
    "flat_truncated": (HEAD + b"-Y 4 +X 8\n" + _flat_pixels(H, W)[:-40], "truncated pixel data"),
    "rle_truncated": (HEAD + b"-Y 4 +X 8\n" + _rle_line(W) * 3 + _rle_line(W)[:6], "truncated RLE"),
    "rle_zero_count": (HEAD + b"-Y 4 +X 8\n" + bytes([2, 2, 0, 8, 0]) + b"\0" * 40, "corrupt RLE literal"),
    "rle_run_overrun": (HEAD + b"-Y 4 +X 8\n" + bytes([2, 2, 0, 8, 128 + 100, 5]) + b"\0" * 40, "overruns"),
    "rle_width_mismatch": (HEAD + b"-Y 4 +X 8\n" + bytes([2, 2, 0, 9]) + b"\0" * 200, "declares width"),
    "old_rle_at_start": (HEAD + b"-Y 4 +X 8\n" + bytes([1, 1, 1, 5]) + _flat_pixels(H, W), "old-style RLE"),
}


def write_hdr_bytes(d: Path, name: str) -> Path:
    p = d / f"{name}.hdr"
    p.write_bytes(BAD_HDR[name][0])
    return p


# ------------------------------------------------------------------------------------------------
# meshes
# ------------------------------------------------------------------------------------------------
def _good_stl(d: Path) -> bytes:
    from ibl_ref.synthetic.synthetic_meshes import make_mesh

    p = d / "good_for_trunc.stl"
    make_mesh("torus").export(str(p))
    return p.read_bytes()


def bad_meshes(d: Path) -> dict:
    """name -> (path, expected message fragment)."""
    import trimesh

    out = {}
    stl = _good_stl(d)
    (d / "trunc.stl").write_bytes(stl[: len(stl) // 2])
    out["truncated_stl"] = (d / "trunc.stl", "truncated")
    (d / "tiny.stl").write_bytes(stl[:40])
    out["tiny_stl"] = (d / "tiny.stl", "truncated")
    write_good_exr(d / "exr_as.obj")
    out["exr_renamed_obj"] = (d / "exr_as.obj", "OpenEXR image")
    trimesh.PointCloud(np.random.default_rng(0).random((100, 3))).export(str(d / "cloud.ply"))
    out["point_cloud_ply"] = (d / "cloud.ply", "point cloud")
    (d / "empty.obj").write_text("")
    out["empty_obj"] = (d / "empty.obj", "empty mesh")
    (d / "nan.obj").write_text("v nan 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    out["nan_vertex"] = (d / "nan.obj", "NaN")
    (d / "degenerate.obj").write_text("v 0 0 0\nv 0 0 0\nv 0 0 0\nf 1 2 3\n")
    out["degenerate_faces"] = (d / "degenerate.obj", "degenerate")
    (d / "vertices_only.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\n")
    out["vertices_only_obj"] = (d / "vertices_only.obj", "triangle")
    (d / "binary.obj").write_bytes(b"v 0 0 0\n\0\0\0\x01\x02")
    out["binary_obj"] = (d / "binary.obj", "binary content")
    out["huge_coordinates"] = (obj_file(d / "huge.obj", scale=1e200), "coordinates up to 1e+200")
    return out


def obj_file(path: Path, scale: float = 1.0, uv: str | None = None) -> Path:
    """An icosphere as OBJ text (vertices times ``scale``; ``uv``: the text of every ``vt`` line, e.g. "nan nan")."""
    import trimesh

    m = trimesh.creation.icosphere(subdivisions=1)
    lines = [f"v {float(a) * scale!r} {float(b) * scale!r} {float(c) * scale!r}" for a, b, c in m.vertices]
    if uv is None:
        lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in m.faces]
    else:
        lines += [f"vt {uv}"] * len(m.vertices)
        lines += [f"f {a + 1}/{a + 1} {b + 1}/{b + 1} {c + 1}/{c + 1}" for a, b, c in m.faces]
    path.write_text("\n".join(lines) + "\n")
    return path


def tiny_latlong(path: Path, value: float, h: int = 8) -> Path:
    """A valid float32 lat-long EXR whose every texel is ``value`` (e.g. 1e-8: below half's range; 1e-40: below
    RGBE's), written through the binding directly."""
    px = np.full((h, 2 * h), value, np.float32)
    return _exr_raw(path, {"R": px, "G": px, "B": px})


def non_utf8_name(d: Path, stem: bytes = b"caf\xe9") -> Path:
    """A valid cube EXR whose file name is not UTF-8 (Latin-1 bytes, as old archives have)."""
    import os

    p = d / os.fsdecode(stem + b".exr")
    return write_good_exr(p)


# ------------------------------------------------------------------------------------------------
# injected file-system failures
# ------------------------------------------------------------------------------------------------
def inject_enospc(monkeypatch, nth: int) -> dict:
    """Make the nth file fsync of ibl_ref.atomic fail with ENOSPC (a disk that fills up at that file)."""
    import errno
    import os

    from ibl_ref import atomic

    real = atomic._fsync_path
    calls = {"n": 0}

    def fake(p, directory=False):
        if not directory:
            calls["n"] += 1
            if calls["n"] == nth:
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return real(p, directory)

    monkeypatch.setattr(atomic, "_fsync_path", fake)
    return calls


def inject_read_only(monkeypatch) -> None:
    """Every file creation by ibl_ref.atomic fails with EROFS (a read-only mount; tests run as root)."""
    import errno
    import os

    from ibl_ref import atomic

    real_open = os.open

    def ro_open(path, flags, *a, **k):
        if flags & os.O_CREAT:
            raise OSError(errno.EROFS, os.strerror(errno.EROFS), str(path))
        return real_open(path, flags, *a, **k)

    monkeypatch.setattr(atomic.os, "open", ro_open)


def inject_read_only_mkdir(monkeypatch) -> None:
    """Every Path.mkdir fails with EROFS."""
    import errno
    import os

    def ro_mkdir(self, *a, **k):
        raise OSError(errno.EROFS, os.strerror(errno.EROFS), str(self))

    monkeypatch.setattr(Path, "mkdir", ro_mkdir)


def make_special(kind: str, p: Path) -> Path:
    """Create a special output target at ``p``: fifo, folder, link_to_dev_null, link_to_dev_full,
    link_to_fifo or symlink_loop."""
    import os

    if kind == "fifo":
        os.mkfifo(p)
    elif kind == "folder":
        p.mkdir()
    elif kind in ("link_to_dev_null", "link_to_dev_full"):
        p.symlink_to("/dev/" + kind.rsplit("_", 1)[1])
    elif kind == "link_to_fifo":
        os.mkfifo(p.parent / "the_fifo")
        p.symlink_to(p.parent / "the_fifo")
    elif kind == "symlink_loop":
        p.symlink_to(p.parent / "loop2")
        (p.parent / "loop2").symlink_to(p)
    else:
        raise ValueError(kind)
    return p


def stand_in_program(folder, name: str, source: str) -> Path:
    """An executable Python script ``folder/name`` running ``source`` with this interpreter: a stand-in for an
    outside program (a peer that hangs, fails or writes garbage)."""
    import sys

    exe = Path(folder) / name
    exe.write_text(f"#!{sys.executable}\n{source}")
    exe.chmod(0o755)
    return exe

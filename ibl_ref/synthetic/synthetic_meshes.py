"""Deterministic test scenes (meshes) for the self-shadowing experiments of Knuth et al. (2014).

The paper renders a teapot and a dragon (Sec. 5, Fig. 1/6/7) and targets virtual garment prototyping
(Sec. 1, 6).  This module builds comparable scenes without external assets:

``sphere_on_plane``  icosphere resting on a square ground plane (two components; plane single-sided,
                     normal +Y) — the classic contact-shadow case.

``torus``            closed torus lying flat (axis +Y), watertight, self-shadowing in the hole.

``teapot``           Newell's teapot tessellated from its 32 published bicubic Bézier patches
                     (``ibl_ref/data/teapot_patches.txt``); **not watertight** (like the original: the
                     handle and spout pierce the body, the lid does not meet the rim).

``cloth``            a draped garment: a periodic grid wrapped around an ellipsoidal torso proxy, hugging
                     the shoulders and flaring towards the hem with sinusoidal folds that decay with
                     height, plus (optionally) the torso itself.

Conventions: +Y up, every object stands on the plane y = 0, faces wound counter-clockwise seen from
outside (outward face normals).  Vertex normals are analytic where the surface is known (sphere:
radial; teapot: Bézier −S_u × S_v averaged across seams), else trimesh's angle-weighted face normals.
``mesh.metadata["part_faces"]`` maps part names to ``[start, stop)`` face-index ranges.
Nothing is random: the cloth's fold phases come from a golden-ratio sequence selected by ``seed``.
"""

from __future__ import annotations

import functools
import inspect
import warnings
from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..errors import IBLError, MeshError
from ..errors import as_path

if TYPE_CHECKING:  # trimesh is imported lazily (≈1 s): the CLI builds its help from this module
    import trimesh

__all__ = [
    "MESH_NAMES",
    "make_mesh",
    "load_mesh",
    "validate_mesh",
    "mesh_sphere_on_plane",
    "mesh_torus",
    "mesh_teapot",
    "mesh_cloth",
    "teapot_patches",
    "bezier_patch_grid",
]


def _int_param(value, name: str, lo: int, hi: int) -> int:
    if isinstance(value, float) and value.is_integer():
        value = int(value)
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or not lo <= int(value) <= hi:
        raise IBLError(f"{name}: expected an integer in [{lo}, {hi}], got {value!r}")
    return int(value)


def _pos_param(value, name: str) -> float:
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise IBLError(f"{name}: expected a number, got {value!r}") from None
    if not np.isfinite(x) or x <= 0:
        raise IBLError(f"{name}: must be a positive finite number, got {value!r}")
    return x


def _nonneg_param(value, name: str) -> float:
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise IBLError(f"{name}: expected a number, got {value!r}") from None
    if not np.isfinite(x) or x < 0:
        raise IBLError(f"{name}: must be a non-negative finite number, got {value!r}")
    return x


def _finish(parts: list[tuple[str, trimesh.Trimesh]], vertex_normals=None) -> trimesh.Trimesh:
    """Concatenate named parts, record their face ranges, set (or compute) vertex normals, validate."""
    import trimesh

    meshes = [m for _, m in parts]
    mesh = trimesh.util.concatenate(meshes) if len(meshes) > 1 else meshes[0]
    ranges, start = {}, 0
    for name, m in parts:
        ranges[name] = [start, start + len(m.faces)]
        start += len(m.faces)
    mesh.metadata["part_faces"] = ranges
    if vertex_normals is not None:
        mesh.vertex_normals = vertex_normals
    _ = mesh.vertex_normals  # computed and cached
    return validate_mesh(mesh, "generated mesh")


# ----------------------------------------------------------------------------------------------
# sphere on plane, torus
# ----------------------------------------------------------------------------------------------
def _ground_plane(size: float, res: int, y: float = 0.0) -> trimesh.Trimesh:
    """Square grid at height y, normal +Y, 2·res² triangles."""
    import trimesh

    t = np.linspace(-size / 2, size / 2, res + 1)
    zz, xx = np.meshgrid(t, t, indexing="ij")  # row i ↔ z, column j ↔ x
    verts = np.stack([xx.ravel(), np.full(xx.size, y), zz.ravel()], axis=1)
    idx = np.arange((res + 1) ** 2).reshape(res + 1, res + 1)
    a, b, c, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, 1:], idx[1:, :-1]  # b = +x, d = +z
    # (a, d, b): (+z) × (+x) = +y  — normal up
    faces = np.concatenate([np.stack([a, d, b], -1).reshape(-1, 3), np.stack([b, d, c], -1).reshape(-1, 3)])
    return trimesh.Trimesh(verts, faces, process=False)


def mesh_sphere_on_plane(radius: float = 1.0, subdivisions: int = 4, plane_size: float = 6.0, plane_res: int = 16,
                         gap: float = 0.0) -> trimesh.Trimesh:
    """Icosphere of ``radius`` resting on (``gap`` above) a square ground plane at y = 0.

    Parameters
    ----------
    radius : float
    subdivisions : int
        Icosphere subdivisions (4 → 5120 triangles).
    plane_size : float
        Side of the square plane (centred under the sphere).
    plane_res : int
        Plane grid segments per side (2·plane_res² triangles).
    gap : float
        Height of the sphere's lowest point above the plane.

    Returns
    -------
    trimesh.Trimesh
        Validated (:func:`validate_mesh`), with ``metadata["part_faces"]``.
    """
    import trimesh

    radius = _pos_param(radius, "radius")
    subdivisions = _int_param(subdivisions, "subdivisions", 0, 7)
    plane_size = _pos_param(plane_size, "plane_size")
    plane_res = _int_param(plane_res, "plane_res", 1, 2048)
    gap = _nonneg_param(gap, "gap")
    sphere = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    radial = sphere.vertices / np.linalg.norm(sphere.vertices, axis=1, keepdims=True)
    sphere.apply_translation([0.0, radius + gap, 0.0])
    plane = _ground_plane(plane_size, plane_res)
    normals = np.concatenate([radial, np.tile([0.0, 1.0, 0.0], (len(plane.vertices), 1))])
    return _finish([("sphere", sphere), ("plane", plane)], vertex_normals=normals)


def mesh_torus(major_radius: float = 1.0, minor_radius: float = 0.35, major_sections: int = 96,
               minor_sections: int = 48) -> trimesh.Trimesh:
    """Watertight torus lying flat on y = 0 (symmetry axis +Y), 2·major·minor sections triangles.

    Parameters
    ----------
    major_radius, minor_radius : float
        Ring radius and tube radius (minor < major).
    major_sections, minor_sections : int
        Segments around the ring and around the tube (default 96 × 48 → 9216 triangles).

    Returns
    -------
    trimesh.Trimesh
        Validated (:func:`validate_mesh`), with ``metadata["part_faces"]``.
    """
    import trimesh

    R = _pos_param(major_radius, "major_radius")
    r = _pos_param(minor_radius, "minor_radius")
    if r >= R:
        raise IBLError(f"torus: minor_radius ({r}) must be smaller than major_radius ({R})")
    ms = _int_param(major_sections, "major_sections", 3, 4096)
    ns = _int_param(minor_sections, "minor_sections", 3, 4096)
    tor = trimesh.creation.torus(major_radius=R, minor_radius=r, major_sections=ms, minor_sections=ns)
    # trimesh's torus has its axis along +Z: rotate +Z → +Y, then lift onto the plane
    tor.apply_transform(trimesh.transformations.rotation_matrix(-np.pi / 2, [1.0, 0.0, 0.0]))
    tor.apply_translation([0.0, r, 0.0])
    if tor.volume < 0:
        tor.invert()
    return _finish([("torus", tor)])


# ----------------------------------------------------------------------------------------------
# teapot
# ----------------------------------------------------------------------------------------------
@functools.lru_cache(maxsize=1)
def teapot_patches():
    """Newell's teapot data from ``ibl_ref/data/teapot_patches.txt``.

    Returns
    -------
    control_points : ndarray (32, 4, 4, 3)
        Control points in the original z-up coordinates (read-only).
    part_names : tuple of 32 str
        ``rim`` (4), ``body`` (8), ``handle`` (4), ``spout`` (4), ``lid`` (8), ``bottom`` (4).
    """
    text = resources.files("ibl_ref").joinpath("data/teapot_patches.txt").read_text()
    patches, names, verts = [], [], {}
    for line in text.splitlines():
        tok = line.split()
        if not tok or tok[0].startswith("#"):
            continue
        if tok[0] == "patch":
            names.append(tok[1])
            patches.append([int(t) for t in tok[2:]])
        elif tok[0] == "v":
            verts[int(tok[1])] = [float(t) for t in tok[2:5]]
    idx = np.array(patches)
    assert idx.shape == (32, 16) and len(verts) == 306, "corrupt teapot data file"
    pts = np.array([verts[i] for i in range(1, 307)])
    cp = pts[idx - 1].reshape(32, 4, 4, 3)
    cp.setflags(write=False)
    return cp, tuple(names)


def _bernstein(t: np.ndarray) -> np.ndarray:
    """Cubic Bernstein basis B_0..B_3 at t, shape (len(t), 4)."""
    s = 1.0 - t
    return np.stack([s**3, 3 * s * s * t, 3 * s * t * t, t**3], axis=-1)


def _bernstein_derivative(t: np.ndarray) -> np.ndarray:
    """d/dt of the cubic Bernstein basis, shape (len(t), 4)."""
    s = 1.0 - t
    return np.stack([-3 * s * s, 3 * s * s - 6 * s * t, 6 * s * t - 3 * t * t, 3 * t * t], axis=-1)


def bezier_patch_grid(control_points: np.ndarray, m: int) -> np.ndarray:
    """Evaluate bicubic Bézier patches on an (m+1) × (m+1) parameter grid.

    S(u, v) = Σ_i Σ_j B_i(u) B_j(v) P_ij with u along the first control-point axis.

    Parameters
    ----------
    control_points : array_like, shape (..., 4, 4, 3)
    m : int
        Segments per parameter.

    Returns
    -------
    ndarray, float64, shape (..., m+1, m+1, 3)
        The patch corners are the corner control points (a Bézier patch interpolates them).
    """
    b = _bernstein(np.linspace(0.0, 1.0, m + 1))
    return np.einsum("ui,vj,...ijk->...uvk", b, b, control_points)


def mesh_teapot(subdiv: int = 16, y_up: bool = True, close_lid_gap: bool = True) -> trimesh.Trimesh:
    """Newell's teapot tessellated from its 32 bicubic Bézier patches.

    Each patch is sampled on a uniform (subdiv+1)² parameter grid and split into 2·subdiv² triangles;
    duplicate vertices along patch seams are merged; the triangles that collapse at the two poles
    (lid knob top, bottom centre: 8 patches with a degenerate first row) are removed, so the mesh has
    ``32·2·subdiv² − 8·subdiv`` triangles (16 256 for the default subdiv = 16), plus ``8·subdiv`` for the lid
    ledge (``close_lid_gap``, 16 384 in all by default).

    Parameters
    ----------
    subdiv : int
        Quads per patch side.
    y_up : bool
        Rotate the original z-up data to +Y up ((x, y, z) → (x, z, −y)); the handle stays at −x, the
        spout at +x, and the teapot stands on y = 0 (height 3.15 in the data's units).
    close_lid_gap : bool
        In the published data the lid ends at radius 1.3 and the body's rim starts at 1.4, both at height 2.4:
        an open annulus through which the pot's *inside* (the back faces of the body sheet) is seen.  At
        render sizes where the annulus is about a pixel wide it shows up as isolated dark pixels along the lid
        rim (their reflection vectors point into the pot).  ``True`` (default) adds the flat ledge the lid rests
        on: 2·4·subdiv triangles (128 at subdiv = 16) joining the lid's outer edge to the rim's inner edge
        (the two edge loops have the same 4·subdiv angles, since both patches sample the same circle), with
        their own vertices and the exact normal of the plane (+y); ``False`` keeps the original open data.

    Returns
    -------
    trimesh.Trimesh
        Validated (:func:`validate_mesh`), with ``metadata["part_faces"]``.

    Notes
    -----
    The patches' winding in the data is consistent; with triangles (a, b, c) = ((i,j), (i,j+1),
    (i+1,j+1)) the face normal is −S_u × S_v, which points outward for every patch (tested).  The mesh
    is **not watertight**: handle and spout ends are open inside the body and the lid (radius 1.3) does
    not touch the rim (radius 1.4; closed by a flat ledge with ``close_lid_gap``, which shares positions but
    not vertices with the lid and the rim).
    """
    import trimesh

    m = _int_param(subdiv, "subdiv", 1, 256)
    cp, names = teapot_patches()
    pts = bezier_patch_grid(np.asarray(cp), m)  # (32, m+1, m+1, 3)
    npp = (m + 1) ** 2
    idx = np.arange(npp).reshape(m + 1, m + 1)
    a, b, c, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, 1:], idx[1:, :-1]
    local = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
    faces = (np.arange(32)[:, None, None] * npp + local[None]).reshape(-1, 3)
    face_part = np.repeat(np.arange(32), len(local))
    # analytic outward normals −S_u × S_v (the data's convention, see Notes); zero at the poles
    t = np.linspace(0.0, 1.0, m + 1)
    b, db = _bernstein(t), _bernstein_derivative(t)
    s_u = np.einsum("ui,vj,pijk->puvk", db, b, np.asarray(cp))
    s_v = np.einsum("ui,vj,pijk->puvk", b, db, np.asarray(cp))
    nrm = -np.cross(s_u, s_v).reshape(-1, 3)
    ln = np.linalg.norm(nrm, axis=1, keepdims=True)
    nrm = np.where(ln > 1e-12, nrm / np.where(ln > 1e-12, ln, 1.0), 0.0)
    verts = pts.reshape(-1, 3)
    if y_up:  # proper rotation (x, y, z) → (x, z, −y), applied to points and normals
        verts = np.stack([verts[:, 0], verts[:, 2], -verts[:, 1]], axis=1)
        nrm = np.stack([nrm[:, 0], nrm[:, 2], -nrm[:, 1]], axis=1)
    # merge seam duplicates: quantise to 1e-9 (seam points are bit-identical: shared control points)
    key = np.round(verts * 1e9).astype(np.int64)
    _, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
    inverse = inverse.reshape(-1)
    nsum = np.zeros((len(first), 3))
    np.add.at(nsum, inverse, nrm)  # average the patches' normals at seam vertices
    verts = verts[first]
    faces = inverse[faces]
    keep = (faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 0] != faces[:, 2])
    faces, face_part = faces[keep], face_part[keep]
    used = np.unique(faces)
    remap = np.full(len(verts), -1)
    remap[used] = np.arange(len(used))
    verts, nsum, faces = verts[used], nsum[used], remap[faces]
    mesh = trimesh.Trimesh(verts, faces, process=False)
    # vertex normals: averaged analytic patch normals; where they cancel (the two poles, where
    # S_v = 0) use trimesh's angle-weighted face normals
    ln = np.linalg.norm(nsum, axis=1, keepdims=True)
    fallback = np.asarray(mesh.vertex_normals)
    vn = np.where(ln > 1e-9, nsum / np.where(ln > 1e-9, ln, 1.0), fallback)
    if close_lid_gap:
        verts, faces, vn, face_part = _lid_ledge(verts, faces, vn, face_part, y_up)
        mesh = trimesh.Trimesh(verts, faces, process=False)
    # part ranges: faces are already grouped by patch and patches by part
    ranges = {}
    for p in np.unique(face_part):
        sel = np.nonzero(face_part == p)[0]
        name = names[p] if p < 32 else "lid_ledge"
        lo, hi = ranges.get(name, [sel[0], sel[-1] + 1])
        ranges[name] = [int(min(lo, sel[0])), int(max(hi, sel[-1] + 1))]
    mesh.metadata["part_faces"] = ranges
    mesh.vertex_normals = vn
    return validate_mesh(mesh, "teapot")


def _lid_ledge(verts, faces, vn, face_part, y_up):
    """Append the flat annulus between the lid's outer edge loop (r ≈ 1.3) and the rim's inner loop (r ≈ 1.4)
    at height 2.4 (module data units), as quads between vertices of equal angle; normal = the up axis."""
    e = np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    u, c = np.unique(e, axis=0, return_counts=True)
    bv = np.unique(u[c == 1])  # vertices on boundary edges
    up = 1 if y_up else 2
    h = verts[bv, up]
    rad = np.hypot(verts[bv, 0], verts[bv, 2 if y_up else 1])
    ang = np.arctan2(verts[bv, 2 if y_up else 1], verts[bv, 0])
    loops = []
    for lo, hi in ((1.25, 1.35), (1.35, 1.45)):
        sel = (np.abs(h - 2.4) < 1e-9) & (rad > lo) & (rad < hi)
        loops.append(bv[sel][np.argsort(ang[sel])])
    inner, outer = loops
    if len(inner) != len(outer) or len(inner) < 3 or not np.allclose(
            np.sort(ang[np.isin(bv, inner)]), np.sort(ang[np.isin(bv, outer)]), atol=1e-9):
        raise MeshError("teapot: lid and rim edge loops do not match; cannot close the lid gap")
    k = len(inner)
    base = len(verts)
    new_v = np.concatenate([verts[inner], verts[outer]])  # own vertices: a crease with the plane's normal
    i = np.arange(k)
    j = (i + 1) % k
    a, b, c2, d = base + i, base + j, base + k + j, base + k + i  # inner_i, inner_j, outer_j, outer_i
    tri = np.concatenate([np.stack([a, c2, b], 1), np.stack([a, d, c2], 1)])
    n_up = np.zeros(3)
    n_up[up] = 1.0
    fn = np.cross(new_v[tri[:, 1] - base] - new_v[tri[:, 0] - base], new_v[tri[:, 2] - base] - new_v[tri[:, 0] - base])
    if np.mean(fn @ n_up) < 0:  # wind so that the face normals point up
        tri = tri[:, [0, 2, 1]]
    nv = np.tile(n_up, (2 * k, 1))
    return (np.concatenate([verts, new_v]), np.concatenate([faces, tri]), np.concatenate([vn, nv]),
            np.concatenate([face_part, np.full(len(tri), 32)]))


# ----------------------------------------------------------------------------------------------
# cloth
# ----------------------------------------------------------------------------------------------
_GOLDEN = 0.6180339887498949


def mesh_cloth(n_around: int = 128, n_down: int = 64, body_radii=(0.5, 0.8, 0.3), body_center_y: float = 1.0,
               top_y: float = 1.55, hem_y: float = 0.08, clearance: float = 0.03, flare: float = 0.25,
               fold_amplitude: float = 0.15, fold_frequencies=(7, 11, 17), hem_wave: float = 0.04, seed: int = 0,
               include_body: bool = True, body_subdivisions: int = 3) -> trimesh.Trimesh:
    """A garment draped over a torso proxy (the paper's virtual-prototyping use case).

    The torso is an ellipsoid with semi-axes ``body_radii`` = (a_x, a_y, a_z) centred at
    (0, body_center_y, 0).  The cloth is a grid of ``n_around`` × (``n_down`` + 1) vertices, periodic
    around the vertical axis (open at the neck and the hem), 2·n_around·n_down triangles
    (16 384 by default).  At angle θ (from +X towards +Z) and height h its distance from the axis is

        R(θ, h) = r_e(θ)·σ(h) + clearance + flare·t^1.5 + fold_amplitude·t²·F(θ, t)

    with r_e(θ) the ellipse radius of the torso's equator, σ(h) = √(1 − ((h − c_y)/a_y)²) above the
    equator (the cloth hugs the shoulders) and 1 below, t = (c_y − h)/(c_y − hem_y) ∈ [0, 1] below
    the equator (0 above), and F = mean_k sin(f_k θ + φ_k + 2t) ∈ [−1, 1] with phases
    φ_k = 2π·frac((k + 1 + seed)·0.618…) (folds growing towards the hem, i.e. decaying with height).
    The hem is lifted by hem_wave·t³·F.  Because fold_amplitude ≤ flare, R ≥ r_e(θ)σ(h) + clearance:
    the cloth never intersects the torso.

    Parameters
    ----------
    n_around, n_down : int
        Grid resolution (columns around, rows of quads from neck to hem).
    body_radii : 3 floats
    body_center_y, top_y, hem_y : float
        Torso centre height; neckline height (within the torso's top half); hem height (≥ 0).
    clearance, flare, fold_amplitude, hem_wave : float
        Distances in scene units; ``fold_amplitude`` must not exceed ``flare``.
    fold_frequencies : ints
        Angular frequencies f_k of the folds.
    seed : int
        Selects the fold phases (deterministic, no RNG).
    include_body : bool
        Add the torso ellipsoid (icosphere with ``body_subdivisions``) as a second part.
    body_subdivisions : int
        Icosphere subdivisions of the torso.

    Returns
    -------
    trimesh.Trimesh
        Validated (:func:`validate_mesh`), with ``metadata["part_faces"]``.

    Raises
    ------
    IBLError
        A parameter out of range (e.g. ``fold_amplitude > flare``, a neckline outside the torso's upper half).
    """
    import trimesh

    na = _int_param(n_around, "n_around", 8, 4096)
    nd = _int_param(n_down, "n_down", 2, 4096)
    try:
        ax, ay, az = (float(x) for x in body_radii)
    except (TypeError, ValueError):
        raise IBLError(f"cloth: body_radii must be 3 numbers, got {body_radii!r}") from None
    for v, nm in ((ax, "body_radii[0]"), (ay, "body_radii[1]"), (az, "body_radii[2]")):
        _pos_param(v, nm)
    cy = _pos_param(body_center_y, "body_center_y")
    top_y, hem_y = float(top_y), _nonneg_param(hem_y, "hem_y")
    if not (cy < top_y < cy + ay):
        raise IBLError(f"cloth: top_y must lie in the torso's upper half ({cy}, {cy + ay}), got {top_y}")
    if not hem_y < cy:
        raise IBLError(f"cloth: hem_y ({hem_y}) must be below body_center_y ({cy})")
    clearance = _nonneg_param(clearance, "clearance")
    flare = _nonneg_param(flare, "flare")
    fold = _nonneg_param(fold_amplitude, "fold_amplitude")
    if fold > flare:
        raise IBLError(f"cloth: fold_amplitude ({fold}) must not exceed flare ({flare}) (cloth would cut the body)")
    hem_wave = _nonneg_param(hem_wave, "hem_wave")
    freqs = [int(f) for f in fold_frequencies]
    seed = _int_param(seed, "seed", 0, 2**31)

    theta = 2 * np.pi * np.arange(na) / na  # (na,)
    h = np.linspace(top_y, hem_y, nd + 1)  # rows from the neck down
    th, hh = np.meshgrid(theta, h, indexing="ij")  # (na, nd+1)
    r_e = 1.0 / np.sqrt(np.cos(th) ** 2 / ax**2 + np.sin(th) ** 2 / az**2)
    sigma = np.where(hh >= cy, np.sqrt(np.clip(1.0 - ((hh - cy) / ay) ** 2, 0.0, 1.0)), 1.0)
    t = np.clip((cy - hh) / (cy - hem_y), 0.0, 1.0)
    phases = [2 * np.pi * (((k + 1 + seed) * _GOLDEN) % 1.0) for k in range(len(freqs))]
    F = np.mean([np.sin(f * th + p + 2.0 * t) for f, p in zip(freqs, phases)], axis=0) if freqs else 0.0 * th
    R = r_e * sigma + clearance + flare * t**1.5 + fold * t**2 * F
    y = hh + hem_wave * t**3 * F
    verts = np.stack([R * np.cos(th), y, R * np.sin(th)], axis=-1).transpose(1, 0, 2).reshape(-1, 3)  # row-major (h, θ)
    idx = np.arange((nd + 1) * na).reshape(nd + 1, na)
    a = idx[:-1, :]
    b = idx[1:, :]  # below a
    c = np.roll(idx, -1, axis=1)[:-1, :]  # next θ
    d = np.roll(idx, -1, axis=1)[1:, :]  # below c
    # (a, c, d): (+θ) × (down) points away from the axis
    faces = np.concatenate([np.stack([a, c, d], -1).reshape(-1, 3), np.stack([a, d, b], -1).reshape(-1, 3)])
    parts = [("cloth", trimesh.Trimesh(verts, faces, process=False))]
    if include_body:
        body = trimesh.creation.icosphere(subdivisions=_int_param(body_subdivisions, "body_subdivisions", 0, 6))
        body.apply_scale(1.0)  # unit sphere
        body.vertices = body.vertices * np.array([ax, ay, az]) + np.array([0.0, cy, 0.0])
        parts.append(("body", body))
    return _finish(parts)


# ----------------------------------------------------------------------------------------------
# dispatch, loading, validation
# ----------------------------------------------------------------------------------------------
_MESHES = {
    "sphere_on_plane": mesh_sphere_on_plane,
    "torus": mesh_torus,
    "teapot": mesh_teapot,
    "cloth": mesh_cloth,
}
MESH_NAMES = tuple(_MESHES)


def make_mesh(name: str, **params) -> trimesh.Trimesh:
    """Generate a deterministic test mesh.

    Parameters
    ----------
    name : str
        One of :data:`MESH_NAMES`: ``"sphere_on_plane"``, ``"torus"``, ``"teapot"``, ``"cloth"`` (module
        docstring).
    **params
        The keyword parameters of the generator ``mesh_<name>`` (their docstrings, or :func:`mesh_help`).

    Returns
    -------
    trimesh.Trimesh
        +Y up, standing on y = 0, outward face normals; ``metadata["part_faces"]`` maps part names to
        ``[start, stop)`` face ranges.

    Raises
    ------
    IBLError
        An unknown name or parameter, an invalid value.

    Examples
    --------
    A unit sphere (subdivided twice: 20·4² triangles) resting on a 6 × 6 plane of 2·4² triangles:

    >>> from ibl_ref.synthetic.synthetic_meshes import make_mesh
    >>> mesh = make_mesh("sphere_on_plane", subdivisions=2, plane_res=4)
    >>> len(mesh.faces), mesh.metadata["part_faces"]
    (352, {'sphere': [0, 320], 'plane': [320, 352]})
    >>> mesh.bounds.tolist()
    [[-3.0, 0.0, -3.0], [3.0, 2.0, 3.0]]
    """
    try:
        fn = _MESHES[name]
    except (KeyError, TypeError):
        raise IBLError(f"unknown synthetic mesh {name!r}; choose one of {', '.join(MESH_NAMES)}") from None
    allowed = list(inspect.signature(fn).parameters)
    unknown = sorted(set(params) - set(allowed))
    if unknown:
        raise IBLError(f"{name}: unknown parameter(s) {unknown}; allowed: {', '.join(allowed)}")
    return fn(**params)


def mesh_help(name: str | None = None) -> str:
    """Parameters with defaults and the first docstring paragraph of one or all mesh generators.

    Parameters
    ----------
    name : str, optional
        One of :data:`MESH_NAMES` (default: all).

    Returns
    -------
    str
    """
    out = []
    for nm in (MESH_NAMES if name is None else (name,)):
        fn = _MESHES[nm]
        params = ", ".join(f"{p.name}={p.default!r}" for p in inspect.signature(fn).parameters.values())
        first = (inspect.getdoc(fn) or "").split("\n\n")[0].replace("\n", " ")
        out.append(f"{nm}: {first}\n    params: {params}")
    return "\n".join(out)


#: largest |vertex coordinate| accepted: products of a few coordinates (areas, normals, projections) stay in float64
MAX_COORDINATE = 1e100


def validate_mesh(mesh, name: str = "mesh", area_eps: float = 0.0) -> trimesh.Trimesh:
    """Check a mesh is usable: faces present, finite vertices of magnitude <= :data:`MAX_COORDINATE`, valid
    indices, not all degenerate.

    Parameters
    ----------
    mesh : trimesh.Trimesh
    name : str, optional
        Names the mesh in messages.
    area_eps : float, optional
        Triangles of at most this area count as degenerate.

    Returns
    -------
    trimesh.Trimesh
        ``mesh`` unchanged.

    Raises
    ------
    MeshError
        Naming ``name`` and the problem.
    """
    import trimesh

    if not isinstance(mesh, trimesh.Trimesh):
        raise MeshError(f"{name}: not a triangle mesh (got {type(mesh).__name__})")
    v = np.asarray(mesh.vertices)
    f = np.asarray(mesh.faces)
    if len(v) == 0 or len(f) == 0:
        raise MeshError(f"{name}: empty mesh ({len(v)} vertices, {len(f)} faces)")
    if not np.all(np.isfinite(v)):
        bad = int(np.sum(~np.all(np.isfinite(v), axis=1)))
        raise MeshError(f"{name}: {bad} vertex/vertices with NaN or Inf coordinates")
    if f.min() < 0 or f.max() >= len(v):
        raise MeshError(f"{name}: face indices out of range [0, {len(v)})")
    vmax = float(np.abs(v).max())
    if vmax > MAX_COORDINATE:
        raise MeshError(f"{name}: coordinates up to {vmax:.3g} in magnitude; areas, normals and the camera's "
                        f"projections multiply coordinates and would overflow float64 (|coordinate| <= "
                        f"{MAX_COORDINATE:g}); rescale the mesh")
    e1 = v[f[:, 1]] - v[f[:, 0]]
    e2 = v[f[:, 2]] - v[f[:, 0]]
    area = 0.5 * np.linalg.norm(np.cross(e1, e2), axis=1)
    scale = float(np.ptp(v, axis=0).max()) or 1.0
    if not np.any(area > max(area_eps, 1e-14 * scale * scale)):
        raise MeshError(f"{name}: all {len(f)} faces are degenerate (zero area)")
    return mesh


_MAGICS = {b"\x76\x2f\x31\x01": "an OpenEXR image", b"#?RADIANCE": "a Radiance HDR image", b"#?RGBE": "a Radiance HDR image",
           b"\x89PNG": "a PNG image", b"PK\x03\x04": "a ZIP archive", b"\x93NUMPY": "a NumPy array file"}


def _sniff_mesh_file(path: Path) -> None:
    """Clear :class:`MeshError` for files that are not what their extension says, before trimesh sees them.

    Checks (file-format facts): other known formats by magic number; a binary STL's size must be
    84 + 50·T bytes for the T triangles its header announces; OBJ / OFF are text (no NUL bytes); a PLY
    whose header declares no ``face`` element (or 0 faces) is a point cloud.
    """
    import struct

    ext = path.suffix.lower()
    size = path.stat().st_size
    with open(path, "rb") as fh:
        head = fh.read(4096)
    for magic, what in _MAGICS.items():
        if head.startswith(magic):
            raise MeshError(f"{path}: is {what}, not a {ext or 'mesh'} mesh file")
    if ext == ".stl" and not head.lstrip().startswith(b"solid"):
        if size < 84:
            raise MeshError(f"{path}: truncated binary STL ({size} bytes, the header alone is 84)")
        (tri,) = struct.unpack_from("<I", head, 80)
        if size != 84 + 50 * tri:
            raise MeshError(f"{path}: truncated or corrupt binary STL: its header announces {tri} triangles "
                            f"({84 + 50 * tri} bytes), the file has {size} bytes")
    if ext in (".obj", ".off") and b"\0" in head:
        raise MeshError(f"{path}: binary content in a {ext} file (OBJ/OFF meshes are text)")
    if ext == ".ply" and head.startswith(b"ply"):
        end = head.find(b"end_header")
        hdr = head[: end if end >= 0 else len(head)].decode("latin-1", "replace").split("\n")
        n_vert = n_face = 0
        for line in hdr:
            f = line.split()
            if len(f) == 3 and f[0] == "element" and f[2].isdigit():
                if f[1] == "vertex":
                    n_vert = int(f[2])
                elif f[1] == "face":
                    n_face = int(f[2])
        if n_face == 0:
            raise MeshError(f"{path}: a point cloud ({n_vert} vertices, no faces); a triangle mesh is needed")


def load_mesh(path_or_name, **params) -> trimesh.Trimesh:
    """A mesh from a name in :data:`MESH_NAMES` (generated with ``params``) or from a file.

    Files are read with ``trimesh.load(path, force="mesh", process=False)`` (scenes are flattened into
    one mesh), validated with :func:`validate_mesh` (before trimesh's processing, which would silently
    drop NaN vertices), then processed (duplicate vertices merged).

    Parameters
    ----------
    path_or_name : str or os.PathLike
        A name in :data:`MESH_NAMES` or a mesh file (OBJ, PLY, STL, … as trimesh reads them).
    **params
        Generator parameters (names only).

    Returns
    -------
    trimesh.Trimesh

    Raises
    ------
    MeshError
        A missing, unreadable, empty or invalid file (one line naming it).
    IBLError
        Parameters given with a file.
    """
    import trimesh

    if isinstance(path_or_name, str) and path_or_name in MESH_NAMES:
        return make_mesh(path_or_name, **params)
    if params:
        raise IBLError(f"load_mesh: parameters {sorted(params)} only apply to generated meshes {MESH_NAMES}")

    path = as_path(path_or_name, "mesh file")
    if not path.is_file():
        raise MeshError(f"{path}: no such mesh file (and not a generated mesh name: {', '.join(MESH_NAMES)})")
    _sniff_mesh_file(path)
    try:
        # process=False: trimesh's processing would silently drop NaN vertices and their faces; its numerical
        # warnings on such data (overflow, NaN casts) are replaced by validate_mesh's one-line errors below
        with warnings.catch_warnings(), np.errstate(all="ignore"):
            warnings.simplefilter("ignore", RuntimeWarning)
            mesh = trimesh.load(str(path), force="mesh", process=False)
    except ImportError as exc:  # trimesh falls back to optional text-encoding detectors on odd bytes
        raise MeshError(f"{path}: cannot read mesh: not a valid {path.suffix or 'mesh'} file "
                        f"(trimesh could not parse it: {exc})") from exc
    except Exception as exc:  # trimesh raises many types for bad files
        raise MeshError(f"{path}: cannot read mesh: {exc}") from exc
    if len(getattr(mesh, "faces", ())) == 0 and path.stat().st_size > 0:
        raise MeshError(f"{path}: no triangles could be read from this {path.stat().st_size}-byte "
                        f"{path.suffix or 'mesh'} file (corrupt, truncated or not a triangle mesh)")
    validate_mesh(mesh, str(path))
    with warnings.catch_warnings(), np.errstate(all="ignore"):  # NaN UVs: refused where a g map needs them
        warnings.simplefilter("ignore", RuntimeWarning)
        mesh.process(validate=False)  # merge duplicate vertices (split normals/uv seams in OBJ files)
    return validate_mesh(mesh, str(path))

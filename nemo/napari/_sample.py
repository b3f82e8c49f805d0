"""Sample data: an analytic NEMO results folder and the synthetic vesicle image.

:func:`write_demo_results` writes a small, fully analytic results tree (icosphere meshes, a
nematic field with four +½ defects at tetrahedron vertices, order, curvature, thickness,
alignment, summaries and a TZCYX image of the shell) in the layout of the workflow
(``results/{dataset}/t{t}/c{c}/``) or of ``nemo run``. It is the napari sample "NEMO demo
results" and the ground truth of the viewer and figure tests. Nothing here imports napari.
"""

from __future__ import annotations

import os
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd
import trimesh

from nemo.io import write_hyperstack
from nemo.mesh import make_mesh, save_mesh
from nemo.tables import write_table


def tetrahedron(rotation: np.ndarray | None = None) -> np.ndarray:
    """Unit vectors to the four vertices of a regular tetrahedron, shape (4, 3)."""
    v = np.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]], dtype=np.float64) / np.sqrt(3)
    return v if rotation is None else v @ np.asarray(rotation).T


def rotation_z(angle_deg: float) -> np.ndarray:
    """Rotation matrix about +z, shape (3, 3)."""
    a = np.radians(angle_deg)
    return np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1.0]])


def defect_field(points: np.ndarray, defects: np.ndarray, charges: np.ndarray) -> np.ndarray:
    """Tangent director field on the unit sphere with point defects (method note §8).

    Stereographic projection from the south pole w = (x + i y) / (1 + z), planar angle
    ψ = Σ q_k arg(w − w_k), lifted with the (conformal) inverse map's tangent basis.

    Parameters
    ----------
    points : ndarray, shape (N, 3)
        Unit vectors.
    defects : ndarray, shape (K, 3)
        Unit vectors of the defects (not at the south pole).
    charges : ndarray, shape (K,)
        Σ charges = 2 keeps the south pole regular.

    Returns
    -------
    ndarray, shape (N, 3)
        Unit tangent directors.
    """
    points = np.array(points, dtype=np.float64)
    pole = points[:, 2] < -1 + 1e-9  # the south pole is regular: evaluate just beside it
    points[pole] = [1e-4, 0.0, -np.sqrt(1 - 1e-8)]
    w = (points[:, 0] + 1j * points[:, 1]) / (1 + points[:, 2])
    wk = (defects[:, 0] + 1j * defects[:, 1]) / (1 + defects[:, 2])
    psi = (np.angle(w[:, None] - wk[None, :]) * np.asarray(charges)[None, :]).sum(axis=1)
    u, v = w.real, w.imag
    s2 = (1 + u**2 + v**2) ** 2
    e_u = np.stack([2 * (1 + v**2 - u**2), -4 * u * v, -4 * u], axis=1) / s2[:, None]
    e_v = np.stack([-4 * u * v, 2 * (1 + u**2 - v**2), -4 * v], axis=1) / s2[:, None]
    e_u /= np.linalg.norm(e_u, axis=1, keepdims=True)
    e_v /= np.linalg.norm(e_v, axis=1, keepdims=True)
    n = np.cos(psi)[:, None] * e_u + np.sin(psi)[:, None] * e_v
    return n / np.linalg.norm(n, axis=1, keepdims=True)


@dataclass
class _Shell:
    """The analytic shell shared by all frames: meshes, per-vertex fields and provenance."""

    inner: trimesh.Trimesh
    outer: trimesh.Trimesh
    unit: np.ndarray  # unit directions of the inner vertices, shape (N, 3)
    centre: np.ndarray
    radius: float
    prov: dict
    intensity: dict = field(init=False)  # layer -> (N,) intensity
    alpha: np.ndarray = field(init=False)  # rotation of layer b's field: 0 at the south pole
    H: np.ndarray = field(init=False)  # mean curvature (the K, k1, k2 follow)
    thickness: np.ndarray = field(init=False)  # NaN where x > 0.9

    def __post_init__(self):
        z_rel, x_rel = self.unit[:, 2], self.unit[:, 0]
        self.intensity = {"a": 100 + 50 * z_rel, "b": 80 + 40 * x_rel}
        self.alpha = 0.5 * np.pi * (z_rel + 1) / 2
        self.H = (1 + 0.2 * z_rel) / self.radius
        self.thickness = 3 + 1.5 * x_rel
        self.thickness[x_rel > 0.9] = np.nan  # rays that found no surface


def _frame_dirs(root: Path, dataset: str, n_frames: int, layout: str,
                image: bool) -> tuple[Path, list[Path], Path | None]:
    """Dataset folder, frame folders and image path (or None) of ``layout``."""
    if layout == "workflow":
        ds = root / dataset
        return ds, [ds / f"t{t}" / "c0" for t in range(n_frames)], root / f"{dataset}.tif" if image else None
    if layout == "run":
        return root, [root], root.parent / f"{root.name}.tif" if image else None
    raise ValueError(f"layout must be 'workflow' or 'run', got {layout!r}")


def _write_image(img_path: Path, centre: np.ndarray, radius: float, spacing: tuple, n_frames: int) -> tuple:
    """Write the TZCYX image of the shell (a Gaussian wall at radius + 2.5); return its ZYX shape."""
    dz, dy, dx = spacing
    shape = tuple(int(np.ceil((centre[i] + radius + 10) / s)) for i, s in zip((2, 1, 0), spacing))
    zz, yy, xx = np.meshgrid(*(np.arange(k) * s for k, s in zip(shape, (dz, dy, dx))), indexing="ij")
    r = np.sqrt((xx - centre[0]) ** 2 + (yy - centre[1]) ** 2 + (zz - centre[2]) ** 2)
    shell = (200 * np.exp(-((r - radius - 2.5) ** 2) / (2 * 1.5**2))).astype(np.uint8)
    data = np.repeat(shell[None, :, None], n_frames, axis=0)  # (T, Z, C, Y, X)
    img_path.parent.mkdir(parents=True, exist_ok=True)
    write_hyperstack(img_path, data, spacing=spacing, axes="TZCYX")
    return shape


def _frame_truth(shell: _Shell, tree, t: int, fdir: Path, degrees_per_frame: float) -> tuple[dict, np.ndarray]:
    """Ground truth of frame t (defects snapped to inner vertices) and the defects' unit vectors."""
    d_unit = tetrahedron(rotation_z(degrees_per_frame * t) @ rotation_z(10.0))
    _, dvert = tree.vertex(d_unit * shell.radius + shell.centre)
    d_unit = shell.unit[dvert]  # defects exactly at vertices: they lie on the surface
    az = np.degrees(np.arctan2(d_unit[:, 1], d_unit[:, 0]))
    pol = np.degrees(np.arccos(np.clip(d_unit[:, 2], -1, 1)))
    return {"t": t, "dir": fdir, "defects": d_unit * shell.radius + shell.centre, "defect_vertex": dvert,
            "azimuth": az, "polar": pol}, d_unit


def _frame_fields(shell: _Shell, d_unit: np.ndarray) -> tuple[dict, np.ndarray]:
    """Directors of layers a and b (b rotated by alpha) and the order S of one frame."""
    rel, alpha = shell.unit, shell.alpha
    na = defect_field(rel, d_unit, np.full(4, 0.5))
    nb = np.cos(alpha)[:, None] * na + np.sin(alpha)[:, None] * np.cross(rel, na)
    geo = np.arccos(np.clip(rel @ d_unit.T, -1, 1)).min(axis=1) * shell.radius
    return {"a": na, "b": nb}, np.tanh(geo / (0.15 * shell.radius))


def _write_layer(shell: _Shell, fdir: Path, L: str, sfx: str, nL: np.ndarray, S: np.ndarray, frame: dict) -> None:
    """Write layer, directors, order and defects tables of layer L of one frame (suffix ``sfx``)."""
    inner, d_pos, dvert = shell.inner, frame["defects"], frame["defect_vertex"]
    vid = np.arange(len(shell.unit))
    sub = vid[::3]
    write_table(pd.DataFrame({"vertex": vid, "intensity": shell.intensity[L]}),
                fdir / f"layer{sfx}.parquet", mesh="mesh.inner.ply", **shell.prov)
    xyz = inner.vertices[sub]
    write_table(pd.DataFrame({"vertex": sub, "x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2],
                              "nx": nL[sub, 0], "ny": nL[sub, 1], "nz": nL[sub, 2],
                              "coherency": S[sub]}), fdir / f"directors{sfx}.parquet")
    write_table(pd.DataFrame({"vertex": vid, "S": S, "nx": nL[:, 0], "ny": nL[:, 1],
                              "nz": nL[:, 2], "x": inner.vertices[:, 0],
                              "y": inner.vertices[:, 1], "z": inner.vertices[:, 2]}),
                fdir / f"order{sfx}.parquet", radius=0.25 * shell.radius)
    write_table(pd.DataFrame({"x": d_pos[:, 0], "y": d_pos[:, 1], "z": d_pos[:, 2],
                              "vertex": dvert, "S": S[dvert], "charge": np.full(4, 0.5) + 0.01 * np.arange(4),
                              "charge_winding": np.full(4, 0.5), "charge_curvature": 0.01 * np.arange(4),
                              "charge_rounded": np.full(4, 0.5)}), fdir / f"defects{sfx}.parquet")


def _write_morphology(shell: _Shell, fdir: Path, named: bool) -> None:
    """Write curvature (and, in the workflow layout, thickness and alignment) tables and the meshes."""
    inner, outer = shell.inner, shell.outer
    vid = np.arange(len(shell.unit))
    H = shell.H
    write_table(pd.DataFrame({"vertex": vid, "H": H, "K": H**2, "k1": H, "k2": H}), fdir / "curvature.parquet")
    if named:
        sub = vid[::3]
        write_table(pd.DataFrame({"vertex": vid, "thickness": shell.thickness}), fdir / "thickness.parquet")
        c = np.cos(2 * shell.alpha[sub])
        xyz = inner.vertices[sub]
        write_table(pd.DataFrame({"vertex": sub, "c": c, "x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2]}),
                    fdir / "align_a_b.parquet")
        save_mesh(inner, fdir / "mesh.inner.ply")
        save_mesh(outer, fdir / "mesh.outer.ply")
    else:
        whole = make_mesh(np.vstack([inner.vertices, outer.vertices]),
                          np.vstack([inner.faces, outer.faces + len(inner.vertices)]))
        save_mesh(whole, fdir / "mesh.ply")
        save_mesh(inner, fdir / "mesh.inner.ply")


def _summary_rows(shell: _Shell, t: int, L: str, S: np.ndarray, frame: dict) -> tuple[list[dict], dict]:
    """Rows of summary/defects.parquet (4) and summary/frames.parquet (1) of layer L of frame t."""
    d_pos, dvert = frame["defects"], frame["defect_vertex"]
    defects = [{"t": t, "c": 0, "layer": L, "x": d_pos[k, 0], "y": d_pos[k, 1], "z": d_pos[k, 2],
                "charge": 0.5, "charge_rounded": 0.5, "S": float(S[dvert[k]]),
                "track_id": k + (0 if L == "a" else 4)} for k in range(4)]
    row = {"t": t, "c": 0, "layer": L, "surface": "inner", "area": float(shell.inner.area),
           "euler_characteristic": 2.0, "S_mean": float(S.mean()), "n_defects": 4, "charge_sum": 2.0,
           "qc_pass": True, "qc_flags": ""}
    return defects, row


def write_demo_results(
    root: str | os.PathLike,
    dataset: str = "demo",
    n_frames: int = 3,
    radius: float = 20.0,
    centre: tuple[float, float, float] = (30.0, 27.0, 25.0),
    spacing: tuple[float, float, float] = (2.0, 1.0, 1.0),
    subdivisions: int = 4,
    degrees_per_frame: float = 15.0,
    layout: str = "workflow",
    image: bool = True,
) -> dict:
    """Write an analytic NEMO results folder and return its ground truth.

    Parameters
    ----------
    root : path
        ``layout="workflow"``: writes ``root/{dataset}/t{t}/c0/`` frames, ``root/{dataset}/
        summary/`` and ``root/{dataset}.tif``; ``layout="run"``: one ``nemo run`` folder
        ``root`` (``mesh.ply``, ``mesh.inner.ply``, ``layer.parquet`` ...; frame 0 only).
    radius : float
        Inner sphere radius (µm); the outer sphere has radius + 5.
    centre : (x, y, z)
        Sphere centre (µm), deliberately not symmetric in x, y, z.
    spacing : (dz, dy, dx)
        Voxel size of the image.
    degrees_per_frame : float
        Rotation of the defect set about +z between frames.

    Returns
    -------
    dict
        ``centre`` (3,), ``radius``, ``frames`` (list of dict: ``t``, ``dir`` (Path),
        ``defects`` (4, 3) physical positions, ``defect_vertex`` (4,), ``azimuth``, ``polar``
        (4,) in degrees), ``image`` (Path or None), ``spacing``, ``dataset_dir``, and the
        analytic field ranges ``intensity_a`` (min, max) etc.
    """
    root = Path(root)
    centre = np.asarray(centre, dtype=np.float64)
    sphere = trimesh.creation.icosphere(subdivisions=subdivisions, radius=1.0)
    unit = np.asarray(sphere.vertices)
    inner = make_mesh(unit * radius + centre, sphere.faces)
    outer_sphere = trimesh.creation.icosphere(subdivisions=max(subdivisions - 1, 1), radius=1.0)
    outer = make_mesh(np.asarray(outer_sphere.vertices) * (radius + 5) + centre, outer_sphere.faces)
    truth: dict = {"centre": centre, "radius": radius, "frames": [], "spacing": spacing,
                   "n_vertices": len(unit)}

    ds, frame_dirs, img_path = _frame_dirs(root, dataset, n_frames, layout, image)
    n_frames = len(frame_dirs)
    truth["dataset_dir"] = ds
    truth["image"] = img_path
    if img_path is not None:
        truth["image_shape"] = _write_image(img_path, centre, radius, spacing, n_frames)

    shell = _Shell(inner, outer, unit, centre, radius,
                   {"image": str(img_path.resolve()) if img_path is not None else None})
    truth["intensity_a"] = (float(shell.intensity["a"].min()), float(shell.intensity["a"].max()))
    named = layout == "workflow"
    rows_def, rows_frames = [], []
    tree = trimesh.proximity.ProximityQuery(inner)
    for t, fdir in enumerate(frame_dirs):
        fdir.mkdir(parents=True, exist_ok=True)
        frame, d_unit = _frame_truth(shell, tree, t, fdir, degrees_per_frame)
        truth["frames"].append(frame)
        directors, S = _frame_fields(shell, d_unit)
        for L in ("a", "b") if named else ("a",):
            _write_layer(shell, fdir, L, f"_{L}" if named else "", directors[L], S, frame)
            defects, row = _summary_rows(shell, t, L, S, frame)
            rows_def += defects
            rows_frames.append(row)
        _write_morphology(shell, fdir, named)
    if named:
        write_table(pd.DataFrame(rows_def), ds / "summary" / "defects.parquet")
        write_table(pd.DataFrame(rows_frames), ds / "summary" / "frames.parquet")
    truth["alpha_range"] = (0.0, float(np.pi / 2))
    return truth


def demo_results_dir() -> Path:
    """Write the demo results into a fresh temporary folder; return ``.../demo``."""
    root = Path(tempfile.mkdtemp(prefix="nemo-demo-"))
    return write_demo_results(root)["dataset_dir"]


def make_demo_results():
    """napari sample: the analytic demo results (layer data tuples)."""
    from nemo.napari.layers import layer_data

    return layer_data(demo_results_dir())


def make_vesicle():
    """napari sample: a small synthetic vesicle image (nemo.synthetic when available).

    Falls back to an analytic fibre-free shell when :mod:`nemo.synthetic` is not installed.
    """
    try:
        from nemo import synthetic  # written by the synthetic-data module; optional here

        data, truth = synthetic.vesicle(radius=30.0, seed=0)
        stack = np.asarray(data)[0, :, 0]
        sp = truth.get("spacing", (1.0, 1.0, 1.0)) if isinstance(truth, dict) else (1.0, 1.0, 1.0)
    except Exception:  # noqa: BLE001 - any signature/absence problem: show the analytic shell instead
        sp = (1.0, 1.0, 1.0)
        zz, yy, xx = np.mgrid[:80, :80, :80].astype(np.float64)
        r = np.sqrt((xx - 40) ** 2 + (yy - 40) ** 2 + (zz - 40) ** 2)
        stack = (200 * np.exp(-((r - 30) ** 2) / (2 * 2.0**2))).astype(np.uint8)
    return [(stack, {"name": "synthetic vesicle", "scale": tuple(sp), "colormap": "gray",
                     "rendering": "mip"}, "image")]

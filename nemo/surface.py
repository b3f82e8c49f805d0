"""Surface reconstruction from 3-D images: blur, threshold, marching cubes, smoothing, split.

Method note §2. A (Z, Y, X) stack becomes a :class:`trimesh.Trimesh` whose vertices are
physical ``x, y, z`` (x = column × dx, y = row × dy, z = plane × dz) and whose faces are wound
so that normals point **out of the bright object** (the solid). Steps:

1. Gaussian blur with σ in µm (σ/spacing voxels per axis, so anisotropic voxels get the same
   physical blur), computed in float32 (a float image whose largest |value| exceeds 1e30, or
   stays below 1e-30, is first divided by it: float32 ends at 3.4e38; the iso-level is relative).
2. Threshold: Yen (default), Otsu or a number -- or a user-supplied binary mask instead.
   With ``edge="half"`` (default for Yen/Otsu) the automatic threshold only tells background
   from object; the surface is placed half-way between the background intensity (the mode of
   the class below the threshold) and the object's plateau (the most populated histogram peak
   above the background that rises above the lowest count between them by a third, and by three
   times the counts' Poisson noise, so no blip of the sparse bright tail). Noise smears that
   peak into the continuum of edge voxels below it; where the histogram of the flat voxels
   (blurred-image gradient below a quarter of the edge's) peaks on its upper flank, that peak is
   the plateau (:func:`_flat_plateau`). That is where a
   blurred step edge really lies: Yen's own level sits on the dim tail of the edge and would
   shift the surface by about 2σ of the total blur. An object with a flat core (deeper than a
   few edge widths, :func:`_interior_plateau`) whose histogram has no peak within 15 % of the
   contrast of the core's median takes that median as its plateau: a small object's histogram
   peaks are its edge voxels. Without a core or a peak (a wall smeared by texture and noise)
   the plateau is the median of the voxels above the threshold, and the level never goes below
   the threshold (a blob keeps the threshold itself). Separate objects of different brightness
   (nuclei) each cross their own half level (:func:`_object_levels`; not with ``refine``).
   A numeric threshold is used as the iso-level as given; a mask is blurred by σ and cut at 0.5.
3. The blurred volume is sampled every ``step`` voxels (the grid scikit-image's marching cubes
   would use with ``step_size=step``) and padded by one sample of its minimum, so that
   objects touching the image border give closed surfaces (flat caps on the border planes); marching
   cubes then runs with the physical spacing. The cap faces (all three vertices on or beyond
   one border plane, i.e. in the padding) are marked right away.
4. Connected components: keep the largest by area (``keep="largest"``) or all.
   :func:`find_objects` counts the separate objects: components not nested inside another one
   (a shell's inner wall is part of the shell) with at least :data:`OBJECT_MIN_AREA` (10 %) of
   the largest one's area (smaller ones are noise). :func:`one_object` refuses to split several
   objects into walls and warns when ``keep="largest"`` ignores some (``nemo.stages.mesh``).
5. Sub-sample snap (:func:`nemo.refine.snap_to_level`): marching cubes interpolates linearly
   between samples, which on coarse z planes leaves terraces where the surface runs nearly
   parallel to them; each vertex moves along its normal (at most a quarter of a sample) to the
   crossing of the same level by the cubic B-spline interpolant of the same field.
   Then Taubin (windowed-sinc) smoothing through PyVista removes the staircase without shrinking.
6. Open surfaces (``border="open"``, the default): a tissue cut by the field of view (a *Hydra*
   foot close-up, an organoid taller than the stack) has no surface beyond the image; its cap is
   fake geometry (fake curvature at its edge, fake topology). The cap faces are dropped after
   the smoothing, the rim vertices put back on their border plane, and the surface is left open
   with its outward winding; ``metadata["nemo_surface"]`` counts the ``cap_faces``,
   ``rim_vertices`` and ``rim_loops``. An object inside the field has no cap and is unchanged.
   ``border="closed"`` keeps the capped surface. Downstream, curvature fits reaching the rim are
   NaN (:func:`nemo.morphology.curvature`), defect contours must not reach it
   (:mod:`nemo.defects`), rays and peeling segments leaving the image are NaN, and renders draw
   the rim.

:func:`split_mesh` separates two walls (inner/outer, basal/apical) by the sign of
``n · (x − centre)`` or ``n · axis``; :func:`fit_sphere` fits a reference sphere.

Orientation convention of split halves: both halves are returned with normals pointing
**away from the centre** (or along ``+axis``). The outer half keeps its winding; the inner half,
whose marching-cubes normals point out of the solid and hence *into the cavity*, is flipped.
For a hollow spherical shell the inner half is then the cavity's sphere with ordinary outward
normals (positive enclosed volume), so peeling "outward" from it samples the shell.
"""

from __future__ import annotations

import warnings
from typing import Literal

import numpy as np
import trimesh
from scipy import ndimage as ndi
from scipy import sparse
from scipy.sparse import csgraph

from nemo._log import listed, logger
from nemo._log import step as log_step
from nemo.errors import NemoError, NemoWarning
from nemo.geometry import close_rim, rim
from nemo.io import check_spacing
from nemo.mesh import (
    face_normals_areas,
    make_mesh,
    merge_coincident_vertices,
    signed_volume,
    split_nonmanifold_vertices,
)

__all__ = [
    "AUTO_SIGMA_SNR",
    "OBJECT_MIN_AREA",
    "SHEET_MAX_WIDTH",
    "cavity_enclosure",
    "count_walls",
    "sheet_flatness",
    "auto_sigma",
    "blur_noise_gain",
    "default_mask_sigma",
    "default_sigma",
    "face_components",
    "find_objects",
    "fit_sphere",
    "keep_components",
    "one_object",
    "sheet_width",
    "parse_threshold",
    "reconstruct",
    "split_mesh",
    "submesh",
]

_MAX_THRESHOLD_SAMPLES = 4_000_000
#: Where the threshold is the level (no plateau), Yen's is the middle of the thresholds whose criterion
#: (its log) lies within this of the best (:func:`_yen_flat_top`): a textured tissue's criterion is flat.
YEN_FLAT_TOP = 0.02
#: Fewest samples along each axis of a stack that :func:`reconstruct` meshes.
MIN_PLANES = 3
#: Flat voxels of the plateau (:func:`_flat_plateau`): blurred-image gradient below this
#: fraction of the median gradient at the edge.
FLAT_GRADIENT = 0.25
#: The flat core of a small object (:func:`_interior_plateau`): its interior lies deeper than this
#: many measured edge widths inside the threshold surface (an erf edge is within 0.003 % of its
#: plateau at 4 σ), the core one width deeper; the core needs this many samples, and the
#: interior's spread and the core's step over the interior at most this fraction of the contrast.
INTERIOR_EDGE_WIDTHS = 4.0
INTERIOR_MIN_SAMPLES = 20
INTERIOR_MAX_SPREAD = 0.15
_MAX_INTERIOR_SAMPLES = 500_000
#: A watershed part meeting the rest of its region over a face at least this fraction of the
#: cross-section of a ball of its volume is a piece of one object, not an object of its own
#: (counted in voxel faces, which a slanted face's staircase inflates: the halves of a nucleus
#: R 7 µm split between two bright foci read 2.2–2.6, two balls R 5 µm 0–1 µm apart under a
#: 1.5 / 0.6 µm PSF 0.37–0.88).
NECK_MAX_FRACTION = 1.4
#: A region without a flat core whose greatest depth reaches this fraction of the radius of a
#: ball of its volume is a compact object (a ball: 1; a 4 µm wall of a 30 µm shell: 0.1), meshed
#: half-way to its deep samples' median (:func:`_deep_plateau`).
BLOB_MIN_DEPTH = 0.5
#: ... and whose greatest depth reaches this many edge widths (its top then within a few % of its
#: plateau: 0.97 of it at the centre of a ball of radius 3 σ).
BLOB_MIN_WIDTHS = 3.0
#: Separate objects meshed at their own half levels (:func:`_object_levels`): regions above the
#: threshold (and cores above the level) of at least this many samples and this fraction of the
#: largest region's samples, shifted where their level differs from the stack's by more than this
#: fraction of its contrast.
OBJECT_LEVEL_MIN_SAMPLES = 64
OBJECT_LEVEL_MIN_FRACTION = 0.01
OBJECT_LEVEL_TOLERANCE = 0.05
#: More cores than this in one region above the threshold are texture, not objects (:func:`_cores`).
OBJECT_LEVEL_MAX_PARTS = 20
#: A separate surface counts as an object when its area is at least this fraction of the largest
#: one's (smaller ones are noise specks or debris, dropped by ``keep="largest"``).
OBJECT_MIN_AREA = 0.1
#: Float images whose largest |value| lies outside this range are divided by it before the
#: float32 blur (which would overflow above 3.4e38 or flush tiny values to zero).
_FLOAT32_SAFE = (1e-30, 1e30)


# --------------------------------------------------------------------------- helpers
def face_components(faces: np.ndarray, n_vertices: int) -> np.ndarray:
    """Connected-component label of every face (faces sharing a vertex are connected).

    Parameters
    ----------
    faces : ndarray, shape (F, 3)
    n_vertices : int

    Returns
    -------
    labels : ndarray, shape (F,)
        Component index per face, ``0 .. n_components - 1``.
    """
    faces = np.asarray(faces)
    if len(faces) == 0:
        return np.zeros(0, dtype=np.int64)
    rows = np.concatenate([faces[:, 0], faces[:, 1]])
    cols = np.concatenate([faces[:, 1], faces[:, 2]])
    graph = sparse.coo_matrix((np.ones(len(rows), dtype=np.int8), (rows, cols)), shape=(n_vertices, n_vertices))
    _, vertex_labels = csgraph.connected_components(graph, directed=False)
    return vertex_labels[faces[:, 0]]


def submesh(mesh: trimesh.Trimesh, face_index: np.ndarray, flip: bool = False) -> trimesh.Trimesh:
    """A new mesh made of some faces of ``mesh``, re-indexed, keeping units and vertex fields.

    Parameters
    ----------
    mesh : trimesh.Trimesh
    face_index : ndarray, shape (K,) of int or shape (F,) of bool
        Faces to keep.
    flip : bool
        Reverse the winding of the kept faces (normals point the other way).

    Returns
    -------
    trimesh.Trimesh
        ``metadata["parent_faces"]`` holds the indices of its faces in ``mesh`` and
        ``metadata["parent_vertices"]`` those of its vertices.
    """
    face_index = np.asarray(face_index)
    if face_index.dtype == bool:
        face_index = np.flatnonzero(face_index)
    faces = np.asarray(mesh.faces)[face_index]
    used = np.unique(faces)
    remap = np.full(len(mesh.vertices), -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    new_faces = remap[faces]
    # a part cut out of a surface may touch itself at single vertices: give each fan its own copy
    _, new_faces, copy_of = split_nonmanifold_vertices(np.asarray(mesh.vertices)[used], new_faces,
                                                       return_index=True)
    used = used[copy_of]
    if flip:
        new_faces = new_faces[:, ::-1]
    fields = {}
    for name, values in mesh.vertex_attributes.items():
        values = np.asarray(values)
        if values.ndim >= 1 and len(values) == len(mesh.vertices):
            fields[name] = values[used]
    out = make_mesh(np.asarray(mesh.vertices)[used], new_faces, unit=getattr(mesh, "units", None) or "um",
                    fields=fields, orient_outward=False)
    if "spacing" in mesh.metadata:
        out.metadata["spacing"] = mesh.metadata["spacing"]
    out.metadata["parent_faces"] = face_index
    out.metadata["parent_vertices"] = used
    return out


def keep_components(mesh: trimesh.Trimesh, keep: Literal["largest", "all"] = "largest") -> trimesh.Trimesh:
    """Keep the largest connected component (by area) of a mesh, or all of it.

    Parameters
    ----------
    mesh : trimesh.Trimesh
    keep : {"largest", "all"}

    Returns
    -------
    trimesh.Trimesh
        ``mesh`` itself for ``"all"`` or a single component; else a re-indexed sub-mesh.
    """
    if keep not in ("largest", "all"):
        raise NemoError(f"keep must be 'largest' or 'all', got {keep!r}")
    if keep == "all" or len(mesh.faces) == 0:
        return mesh
    labels = face_components(mesh.faces, len(mesh.vertices))
    n = int(labels.max()) + 1
    if n == 1:
        return mesh
    _, areas = face_normals_areas(np.asarray(mesh.vertices), np.asarray(mesh.faces))
    comp_area = np.bincount(labels, weights=areas, minlength=n)
    best = int(np.argmax(comp_area))
    logger.info("keeping the largest of %d components (%.4g of %.4g area units)", n, comp_area[best], comp_area.sum())
    return submesh(mesh, labels == best)


def _winding_numbers(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray, chunk: int = 250_000) -> np.ndarray:
    """Generalised winding number of each point w.r.t. a triangle surface (solid angles / 4π).

    ±1 inside a closed surface (the sign follows its orientation), 0 outside.
    """
    w = np.zeros(len(points))
    for s in range(0, len(faces), chunk):
        tri = vertices[faces[s:s + chunk]]  # (F, 3, 3)
        for i, p in enumerate(points):
            a, b, c = tri[:, 0] - p, tri[:, 1] - p, tri[:, 2] - p
            la, lb, lc = (np.linalg.norm(v, axis=1) for v in (a, b, c))
            num = np.einsum("ij,ij->i", a, np.cross(b, c))
            den = (la * lb * lc + np.einsum("ij,ij->i", a, b) * lc + np.einsum("ij,ij->i", a, c) * lb
                   + np.einsum("ij,ij->i", b, c) * la)
            w[i] += 2.0 * np.arctan2(num, den).sum()
    return w / (4.0 * np.pi)


def find_objects(mesh: trimesh.Trimesh, min_fraction: float = OBJECT_MIN_AREA) -> list[dict]:
    """The separate objects of a reconstructed surface (closed, or open where the image cuts it).

    An object is a connected component that is **not nested** inside another component and
    whose area is at least ``min_fraction`` of the largest component's. A hollow shell's inner
    wall lies inside its outer wall and belongs to the same object; so does anything else
    inside it. Smaller components (noise specks) are not objects. Nesting is tested with the
    winding number of one vertex of the candidate (off its rim when it has one) with respect to
    the larger components whose bounding box holds its own. An open container (a surface cut
    by the image border, ``border="open"``) is first closed by a fan over each rim loop
    (:func:`nemo.geometry.close_rim`): for a rim on a border plane that is the flat cap the
    open surface lost, so a cut shell's inner wall is still nested in its outer wall and two
    cut objects side by side stay two objects. A rim running over several border planes gets no
    flat cap from a fan, so the pieces that the cut took from one closed surface (recorded by
    :func:`reconstruct` in :data:`CLOSED_SURFACE_FIELD`: the two faces of a sheet cut on every
    side) are one object whatever their nesting: only the largest of them is a candidate.

    Parameters
    ----------
    mesh : trimesh.Trimesh
    min_fraction : float
        Relative area below which a component is noise.

    Returns
    -------
    list of dict
        Largest first: ``component`` (label of :func:`face_components`), ``components`` (it and
        the other pieces of its closed surface, largest first), ``area``, ``radius``
        (of the sphere of the same area, ``sqrt(area / 4π)``) and ``centre`` (area-weighted
        centroid, x, y, z) of each object's outermost surface.
    """
    vertices, faces = np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces)
    if len(faces) == 0:
        return []
    labels = face_components(faces, len(vertices))
    n = int(labels.max()) + 1
    _, areas = face_normals_areas(vertices, faces)
    comp_area = np.bincount(labels, weights=areas, minlength=n)
    group = _closed_surface_groups(mesh, faces, labels, n)
    # a piece is a candidate when it is the largest of its group (the pieces the image border cut apart)
    largest = np.lexsort((-comp_area, group))
    lead = largest[np.r_[True, group[largest][1:] != group[largest][:-1]]]
    big = lead[comp_area[lead] >= min_fraction * comp_area.max()]
    big = big[np.argsort(-comp_area[big], kind="stable")]
    # bounding box of every component (vertices sorted by component label, rim vertices last)
    vlab = np.full(len(vertices), -1, dtype=np.int64)
    vlab[faces.ravel()] = np.repeat(labels, 3)
    order = np.lexsort((rim(faces, len(vertices))["vertices"], vlab))
    order = order[vlab[order] >= 0]
    starts = np.searchsorted(vlab[order], np.arange(n))
    lo, hi = np.minimum.reduceat(vertices[order], starts), np.maximum.reduceat(vertices[order], starts)
    probe = vertices[order[starts]]  # off the rim where the component has such a vertex
    tol = 1e-9 * max(1.0, float(np.abs(vertices).max()))
    nested = np.zeros(len(big), dtype=bool)
    for j, cj in enumerate(big[:-1]):  # containers: every larger component
        cand = np.arange(j + 1, len(big))
        cand = cand[~nested[cand] & (lo[big[cand]] >= lo[cj] - tol).all(1) & (hi[big[cand]] <= hi[cj] + tol).all(1)]
        if len(cand):
            nested[cand] |= np.abs(_winding_numbers(probe[big[cand]], *close_rim(vertices, faces[labels == cj]))) > 0.5
    centroids = vertices[faces].mean(axis=1) * areas[:, None]
    centre = np.stack([np.bincount(labels, weights=centroids[:, k], minlength=n) for k in range(3)], 1)
    return [{"component": int(c), "components": [int(c), *sorted((int(k) for k in np.flatnonzero(group == group[c])
                                                                   if k != c), key=lambda k: -comp_area[k])],
             "area": float(comp_area[c]), "radius": float(np.sqrt(comp_area[c] / (4 * np.pi))),
             "centre": centre[c] / max(comp_area[c], 1e-300)} for c in big[~nested]]


def regions_per_object(mesh: trimesh.Trimesh, found: list[dict], points: np.ndarray) -> list[int]:
    """How many of ``points`` (x, y, z; the brightest samples of the image's separate bright regions,
    ``metadata["nemo_surface"]["region_peaks"]``) lie inside each object of :func:`find_objects`.

    Two regions the image keeps apart (their component tree parts them; :func:`_object_levels`)
    can still be one iso-surface: nuclei that touch, or lie closer than the blur along z. Such an
    object holds two or more points, and its area and volume are theirs together.

    Returns
    -------
    list of int
        Per object of ``found`` (its outermost surface closed over its rim by
        :func:`nemo.geometry.close_rim`, so a cut object counts too); 0 each without points.
    """
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if not len(points):
        return [0] * len(found)
    vertices, faces = np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces)
    labels = face_components(faces, len(vertices))
    order = np.argsort(labels, kind="stable")  # faces grouped by component once, not once per object
    starts = np.searchsorted(labels[order], np.arange(int(labels.max()) + 2))
    counts = []
    for obj in found:  # a loop over the objects
        own = faces[order[starts[obj["component"]]:starts[obj["component"] + 1]]]
        lo, hi = vertices[own].min(axis=(0, 1)), vertices[own].max(axis=(0, 1))
        near = points[((points >= lo) & (points <= hi)).all(axis=1)]
        inside = np.abs(_winding_numbers(near, *close_rim(vertices, own))) > 0.5 if len(near) else []
        counts.append(int(np.sum(inside)))
    return counts


def _closed_surface_groups(mesh: trimesh.Trimesh, faces: np.ndarray, labels: np.ndarray, n: int) -> np.ndarray:
    """Group of each of the ``n`` components: those cut from one closed surface by ``border="open"``
    (:data:`CLOSED_SURFACE_FIELD`) share one; without that field every component is its own."""
    closed = mesh.vertex_attributes.get(CLOSED_SURFACE_FIELD)
    if closed is None or len(closed) != len(mesh.vertices):
        return np.arange(n)
    first_face = np.unique(labels, return_index=True)[1]
    key = np.asarray(closed, dtype=np.float64)[faces[first_face, 0]]
    key = np.where(key >= 0, key, -1.0 - np.arange(n))  # no record: a group of its own
    return np.unique(key, return_inverse=True)[1]


def turn_out_dark_objects(mesh: trimesh.Trimesh, objects: list[dict] | None = None) -> tuple[trimesh.Trimesh, int]:
    """Turn out the objects whose closed surface encloses the dark side of the image.

    Marching cubes winds a surface with its normals towards the darker side. An object
    (:func:`find_objects`) that is closed, not nested in another surface, and encloses a
    negative volume is a dark region in a foreground that fills the stack around it (the image
    border's caps removed, ``border: open``): a vesicle in a stained medium, or a mask whose
    background class was given. Its faces, and those of every surface nested in it, are turned
    so that the normals point out of the enclosed region, as for a bright object.

    ``objects`` is :func:`find_objects` of ``mesh`` when already made (turning faces changes
    neither the components, their areas nor their nesting, so it still holds after).

    Returns
    -------
    mesh : trimesh.Trimesh
        ``mesh`` itself when nothing is turned, else a copy with the turned faces.
    n_turned : int
        Objects turned out.
    """
    vertices, faces = np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces)
    labels = face_components(faces, len(vertices))
    rim_vertex = rim(faces, len(vertices))["vertices"]
    components, first_face = np.unique(labels, return_index=True)
    turn = np.zeros(len(faces), dtype=bool)
    n_turned = 0
    for obj in find_objects(mesh) if objects is None else objects:  # a loop over the few objects
        own = labels == obj["component"]
        tri = vertices[faces[own]]
        volume = np.einsum("ij,ij->", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])) / 6.0
        if rim_vertex[faces[own]].any() or volume >= 0:
            continue
        others = np.setdiff1d(components, [obj["component"]])
        probes = vertices[faces[first_face[others], 0]]  # one vertex of every other component
        inside = others[np.abs(_winding_numbers(probes, vertices, faces[own])) > 0.5]
        turn |= own | np.isin(labels, inside)
        n_turned += 1
    if not n_turned:
        return mesh, 0
    turned = mesh.copy()
    turned.faces = np.where(turn[:, None], faces[:, ::-1], faces)
    turned.metadata.update(mesh.metadata)
    return turned, n_turned


def _describe_objects(objects: list[dict], unit: str) -> str:
    return listed(
        f"area {o['area']:.4g} {unit}² (radius of equal area {o['radius']:.4g} {unit}) centred at "
        f"({o['centre'][0]:.4g}, {o['centre'][1]:.4g}, {o['centre'][2]:.4g})" for o in objects)


#: Most voxels :func:`image_noise` looks at (a strided sample; robust statistics need no more).
NOISE_SAMPLE_VOXELS = 4_000_000
#: Most of a sample that may sit at its minimum for :func:`background_spread` to read a spread.
MAX_CLIPPED_FRACTION = 0.9


def background_spread(values: np.ndarray) -> tuple[float | None, float | None]:
    """Centre and standard deviation of background intensities, robust to clipping at the bottom.

    The centre μ and spread σ of a Gaussian are the line ``x = μ + σ Φ⁻¹(F(x))`` fitted to the
    empirical distribution F at nine cuts x between its quantiles ``max(¼, p0 + (1 − p0)/20)``
    and ``max(¾, p0 + (1 − p0)/2)``, ``p0`` being the fraction of values at the minimum. Without
    clipping that is the interquartile range (robust to outliers, as a MAD). With clipping (a
    camera offset of 0, an 8-bit image whose dark background lost its lower half to 0) the values
    at the minimum are censored and only the quantiles above them are used; a median/MAD reads
    such an image as noise-free (the SNR-5 vesicles did). Only a minimum at or below 0 counts as
    clipped: a flat background above 0 (a clean image whose blurred edges form a sparse tail)
    is noise-free. Integer data are cut half-way between levels, so 8-bit rounding does not bias
    small spreads.

    Parameters
    ----------
    values : ndarray, shape (N,)
        Background intensities (any dtype; NaN not allowed).

    Returns
    -------
    centre, spread : float or None
        None when undefined (fewer than 10 values, or more than :data:`MAX_CLIPPED_FRACTION`
        but not all of them at a minimum of 0). Half or more of the values equal: spread 0.
    """
    from scipy.special import ndtri  # Φ⁻¹

    values = np.sort(np.asarray(values, dtype=np.float64).ravel())
    if values.size < 10:
        return None, None
    # clipping happens at 0 (an unsigned camera or an 8-bit image); a flat background above 0 with
    # blurred edges is a clean image, not a clipped one
    clipped = np.searchsorted(values, values[0], side="right") / values.size if values[0] <= 0 else 0.0
    if clipped > MAX_CLIPPED_FRACTION:
        return (float(values[0]), 0.0) if clipped >= 1.0 else (None, None)
    q = np.linspace(max(0.25, clipped + 0.05 * (1 - clipped)), max(0.75, clipped + 0.5 * (1 - clipped)), 9)
    cuts = np.unique(np.quantile(values, q))
    if len(cuts) == 1:  # most of the background is one value: no noise
        return float(cuts[0]), 0.0
    if np.array_equal(values, np.round(values)):  # integer counts: cut half-way between levels
        cuts = np.unique(np.floor(cuts) + 0.5)
    below = np.searchsorted(values, cuts, side="right") / values.size
    keep = (below > 0) & (below < 1)
    if keep.sum() < 2:
        return None, None
    spread, centre = np.polyfit(ndtri(below[keep]), cuts[keep], 1)  # cut = centre + spread Φ⁻¹(F(cut))
    return float(centre), float(spread)


def _split_sample(sample: np.ndarray, blurred: np.ndarray, level: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(inside mask, background values, core values) of a raw sample split by its blurred copy.

    Background: the raw values whose blurred value is below ``level``, two samples away from the
    object (its blurred edge is not background); core: the object eroded by one sample. Split by
    the blurred copy, not the raw values, so the noise of either side is not cut at ``level``.
    """
    inside = blurred >= level
    return inside, sample[~ndi.binary_dilation(inside, iterations=2)], sample[ndi.binary_erosion(inside)]


#: Full scales of the integer detectors (8- to 16-bit, unsigned and signed 16-bit) that
#: :func:`saturated_fraction` knows.
DETECTOR_FULL_SCALES = (*(2**bits - 1 for bits in (8, 10, 12, 14, 16)), 2**15 - 1)


def saturated_fraction(values: np.ndarray, dtype: np.dtype | None = None) -> float | None:
    """Fraction of ``values`` at the largest of them when that is a detector's full scale.

    A saturated object's plateau reads low, so the half level between background and plateau,
    and with it every wall, moves outward (a bright shell comes out thicker). Only images of an
    integer ``dtype`` whose maximum is a full scale of :data:`DETECTOR_FULL_SCALES` count: a
    probability map's plateau at 1.0 or a label image is not saturation.

    Parameters
    ----------
    values : ndarray, shape (M,)
        Raw intensities (e.g. the object's core), any numeric dtype.
    dtype : numpy dtype, optional
        The image's dtype (default: that of ``values``; give it when they were converted).

    Returns
    -------
    float or None
        The fraction in [0, 1]; 0 when the maximum is no full scale; None for a non-integer
        ``dtype`` or no values.
    """
    values = np.asarray(values)
    if values.size == 0 or not np.issubdtype(values.dtype if dtype is None else np.dtype(dtype), np.integer):
        return None
    top = int(values.max())
    return float(np.count_nonzero(values == top)) / values.size if top in DETECTOR_FULL_SCALES else 0.0


#: A mask's surface is flagged when the segmented channel's own edge lies farther from it than
#: this many of the largest voxel sides (the median over the vertices; a mask dilated by one
#: lateral voxel reads half of it, a mask of the shell 2 µm larger 1.8 at 1 µm planes).
MASK_MAX_OFFSET_VOXELS = 1.0
#: How far (in the largest voxel side) the mask check looks along each normal, in and out.
MASK_REACH_VOXELS = 3


def mask_edge_offset(mesh: trimesh.Trimesh, image: np.ndarray, spacing: tuple[float, float, float],
                     labels: np.ndarray | None = None) -> dict:
    """How well a mask's surface follows the segmented channel's own edges.

    A mask from another time point, channel or class of a probability map is meshed as given and
    passed quality control (an independent review: a mask of t 0 on t 1, volume −23 %; the cavity
    class of a 3-class map meshed as the object). The channel's half level is taken half-way
    between the medians (over the vertices) of the brightest sample up to three voxels inside and the
    darkest up to three voxels outside along the normals (a thin wall or a small nucleus peaks
    within that depth); ``mask_contrast`` compares the samples one voxel in and out;
    each vertex's offset to where the image (blurred by a voxel) crosses it along the normal is
    found within three voxels (:func:`nemo.refine.refine_vertices`' search).

    Parameters
    ----------
    mesh : trimesh.Trimesh
        The mask's surface (physical x, y, z, outward normals).
    image : ndarray, shape (Z, Y, X)
        The segmented channel.
    spacing : (dz, dy, dx)
    labels : ndarray of int, shape (N,), optional
        Each vertex's object (0, 1, …; :func:`nemo.objects.vertex_labels`): each object gets its
        own half level and numbers (one label stale among several passed with a frame's median).

    Returns
    -------
    dict
        ``mask_offset`` (median |offset| over the vertices whose profile stays in the image, one
        without an edge in reach counted as the reach, or the length of the translation that best
        explains the signed offsets when larger: a rigidly shifted label; NaN without such vertices),
        ``mask_offset_limit`` (:data:`MASK_MAX_OFFSET_VOXELS` × the largest voxel side),
        ``mask_edges_found`` (fraction of vertices with an edge in reach) and ``mask_contrast``
        (median inside − median outside, in the image's units: negative when the mask holds the
        darker side); with ``labels`` of several objects, a list of each object's for the three.
    """
    from nemo.refine import _edge_offsets, _neighbour_matrix

    vertices, faces = np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces)
    voxel = float(max(spacing))
    out = {"mask_offset": float("nan"), "mask_offset_limit": MASK_MAX_OFFSET_VOXELS * voxel,
           "mask_edges_found": 0.0, "mask_contrast": float("nan")}
    normals = _vertex_normals(mesh)
    ok = np.isfinite(normals).all(axis=1)
    if not ok.any():
        return out
    smooth = ndi.gaussian_filter(np.asarray(image, dtype=np.float32), [voxel / d for d in spacing], truncate=3.0)
    per_voxel = np.asarray(spacing, dtype=np.float64)[::-1]  # dx, dy, dz

    def along(depths: np.ndarray) -> np.ndarray:  # (n, D) samples at signed depths (voxels) along the normals
        pts = vertices[ok][:, None] + depths[None, :, None] * voxel * normals[ok][:, None]
        return ndi.map_coordinates(smooth, (pts.reshape(-1, 3) / per_voxel)[:, ::-1].T, order=1,
                                   mode="nearest").reshape(len(pts), len(depths))

    labels = np.zeros(len(vertices), dtype=np.int64) if labels is None else np.asarray(labels, dtype=np.int64)
    n_objects = int(labels.max()) + 1
    order = np.argsort(labels, kind="stable")  # each object's vertices, once: O(N) over all objects
    groups = np.split(order, np.searchsorted(labels[order], np.arange(1, n_objects)))

    def per_object(values: np.ndarray, where: np.ndarray) -> np.ndarray:  # each object's median of values[where]
        return np.array([np.median(values[g][where[g]]) if where[g].any() else np.nan for g in groups])

    near = np.full((len(vertices), 2), np.nan)
    near[ok] = along(np.array([-1.0, 1.0]))
    contrast = per_object(near[:, 0], ok) - per_object(near[:, 1], ok)
    # the plateau: the brightest sample up to 3 voxels in (a thin wall or a small nucleus peaks
    # before that depth, and a fixed depth would read its lumen or far side); the background: the
    # darkest up to 3 voxels out; each object's own
    depths = np.arange(1, 2 * MASK_REACH_VOXELS + 1) / 2.0  # every half voxel
    top, bottom = np.full(len(vertices), np.nan), np.full(len(vertices), np.nan)
    top[ok], bottom[ok] = along(-depths).max(axis=1), along(depths).min(axis=1)
    level = 0.5 * (per_object(top, ok) + per_object(bottom, ok))
    reach = np.full(len(vertices), MASK_REACH_VOXELS * voxel)
    offsets, left = _edge_offsets(smooth, vertices, np.where(ok[:, None], normals, np.nan), reach, per_voxel,
                                  8 * MASK_REACH_VOXELS,  # profile samples each side: 8 per voxel
                                  _neighbour_matrix(faces, len(vertices)), "level", level[labels][:, None], None)
    found = np.isfinite(offsets) & ~left & ok
    # no edge within reach counts as the reach: dropped, a third of a stale label's vertices let a
    # 4.5 µm shift read 1.2 µm, under the limit (an independent review)
    offset = per_object(np.where(found, np.abs(offsets), MASK_REACH_VOXELS * voxel), ~left & ok)
    # a label shifted rigidly by s reads a median |offset| of s/2 (|s·n| over a sphere): the shift
    # that best explains the signed offsets (least squares, offset ≈ n·s) counts at its length
    shift = np.array([_shift_length(normals[g][found[g]], offsets[g][found[g]]) for g in groups])
    offset = np.fmax(offset, shift)
    share = np.array([found[g].mean() if len(g) else 0.0 for g in groups])

    def value(x: np.ndarray):  # one object: a number (as before objects), several: a list
        return float(x[0]) if n_objects == 1 else [float(v) for v in x]

    return {**out, "mask_offset": value(offset), "mask_edges_found": value(share), "mask_contrast": value(contrast)}


def _shift_length(normals: np.ndarray, offsets: np.ndarray) -> float:
    """Length of the translation s that best explains signed offsets along unit normals (n · s ≈
    offset, least squares); NaN with fewer than 10 of them or normals that span no volume (a flat
    piece cannot show a shift along itself)."""
    if len(offsets) < 10:
        return float("nan")
    gram = normals.T @ normals
    if np.linalg.cond(gram) > 1e6:
        return float("nan")
    return float(np.linalg.norm(np.linalg.solve(gram, normals.T @ offsets)))


def image_noise(volume: np.ndarray, level: float) -> dict:
    """Background noise and signal-to-noise ratio of a stack, split at the surface's iso-level.

    Parameters
    ----------
    volume : ndarray, shape (Z, Y, X)
        The raw (unblurred) segmented channel.
    level : float
        The iso-level of the surface (in ``volume``'s intensity units).

    Returns
    -------
    dict
        ``noise``: the background's spread (:func:`background_spread`, robust to clipping) over
        a strided sample (about :data:`NOISE_SAMPLE_VOXELS` voxels) split by its copy blurred
        by one sample (:func:`_split_sample`); ``snr``: (median of the object's core − background
        centre) / ``noise``; ``saturated``: the fraction of the core's voxels at the detector's
        full scale (:func:`saturated_fraction`; None for a two-valued image, a mask saved as an
        image); ``background``: the background's centre (:func:`background_spread`). None where
        undefined (no noise, or too few voxels on a side).
    """
    step = max(1, int(np.ceil((volume.size / NOISE_SAMPLE_VOXELS) ** (1 / 3))))
    raw = np.asarray(volume[::step, ::step, ::step])
    sample = np.nan_to_num(raw.astype(np.float32, copy=False))
    _, background, core = _split_sample(sample, ndi.gaussian_filter(sample, 1.0), level)
    if core.size < 10:
        return {"noise": None, "snr": None, "saturated": None, "background": None}
    binary = np.unique(sample.ravel()[:: max(1, sample.size // 100_000)]).size <= 2  # a mask saved as an image
    saturated = None if binary else saturated_fraction(core, raw.dtype)
    centre, noise = background_spread(background)
    if centre is None:
        return {"noise": None, "snr": None, "saturated": saturated, "background": None}
    snr = (float(np.median(core)) - centre) / noise if noise > 0 else None
    return {"noise": noise, "snr": snr, "saturated": saturated, "background": centre}


def one_object(mesh: trimesh.Trimesh, split: bool, keep: Literal["largest", "all"] = "largest",
               min_fraction: float = OBJECT_MIN_AREA, objects: list[dict] | None = None) -> trimesh.Trimesh:
    """Check that a reconstructed surface holds one object (:func:`find_objects`) before analysis.

    Parameters
    ----------
    mesh : trimesh.Trimesh
        The whole surface (every component).
    split : bool
        The surface is to be split into inner/outer walls.
    keep : {"largest", "all"}
        ``"largest"``: with several objects, the largest (with the walls nested in it when
        splitting, else its largest component) and a warning naming the others. ``"all"``:
        everything; several objects with ``split`` are an error (their walls would be mixed).
    min_fraction : float
        Relative area below which a component is noise, not an object.
    objects : list of dict, optional
        :func:`find_objects` of ``mesh`` at ``min_fraction``, when already made.

    Returns
    -------
    trimesh.Trimesh
        The surface to analyse, with ``mesh``'s metadata and ``metadata["n_objects"]``, the
        number of objects found (also recorded in ``mesh.metadata``).

    Raises
    ------
    NemoError
        ``split`` with ``keep="all"`` and several objects.
    """
    objects = find_objects(mesh, min_fraction) if objects is None else objects
    mesh.metadata["n_objects"] = len(objects)  # carried to the result (quality control)
    unit = getattr(mesh, "units", None) or "um"
    if len(objects) < 2 or keep == "all":
        if len(objects) > 1 and split:
            raise NemoError(
                f"the image holds {len(objects)} objects (separate surfaces, not nested in each other, of at "
                f"least {min_fraction:.0%} of the largest one's area): {_describe_objects(objects, unit)}. "
                "Splitting them all into one inner and one outer wall would mix their walls: set `keep` largest "
                "(config mesh.keep: largest) to analyse the largest, give a `mask` selecting one object "
                "(config: the dataset's mask), or crop the image to one object"
            )
        if len(objects) > 1:
            logger.info("keeping all %d objects: %s", len(objects), _describe_objects(objects, unit))
        return mesh if split or keep == "all" else _with_metadata(keep_components(mesh, keep), mesh)
    warnings.warn(
        f"the image holds {len(objects)} objects: analysing the largest ({_describe_objects(objects[:1], unit)}) "
        f"and ignoring {len(objects) - 1} other object(s): {_describe_objects(objects[1:], unit)}; set `keep` all "
        "(config mesh.keep: all) to analyse each of them, select one with a `mask` (with a label image: "
        "mask_labels), or crop the image",
        NemoWarning, stacklevel=3)
    if split:  # the largest object with its own inner walls (components nested in it)
        return _with_metadata(objects_with_nested(mesh, [objects[0]["components"]])[0], mesh)
    return _with_metadata(keep_components(mesh, keep), mesh)


def objects_with_nested(mesh: trimesh.Trimesh, objects: list[list[int]]) -> list[trimesh.Trimesh]:
    """Each object (a list of its components of ``mesh``, :func:`find_objects`: its largest piece
    first) with every component lying inside its largest piece (winding number). The components,
    their probes and bounding boxes are found once, and only the components whose probe lies in
    the bounding box of an object's largest piece are tested (300 nuclei: 32 s → under 2 s)."""
    vertices, faces = np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces)
    labels = face_components(faces, len(vertices))
    n = int(labels.max()) + 1 if labels.size else 0
    first_face = np.unique(labels, return_index=True)[1]
    off_rim = ~rim(faces, len(vertices))["vertices"][faces]  # (F, 3)
    # one vertex of every component, off the rim where its first face has one
    probes = vertices[faces[first_face, np.argmax(off_rim[first_face], axis=1)]]
    corners, owner = vertices[faces.ravel()], np.repeat(labels, 3)
    low, high = np.full((n, 3), np.inf), np.full((n, 3), -np.inf)
    np.minimum.at(low, owner, corners)
    np.maximum.at(high, owner, corners)
    order = np.argsort(labels, kind="stable")
    starts = np.searchsorted(labels[order], np.arange(n + 1))
    out = []
    for components in objects:  # a loop over objects
        largest = components[0]
        inside = np.zeros(n, dtype=bool)
        near = np.flatnonzero(np.all((probes >= low[largest]) & (probes <= high[largest]), axis=1))
        shell = close_rim(vertices, faces[order[starts[largest]:starts[largest + 1]]])
        inside[near] = np.abs(_winding_numbers(probes[near], *shell)) > 0.5
        inside[components] = True
        out.append(submesh(mesh, inside[labels]))
    return out


def _with_metadata(out: trimesh.Trimesh, mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """``out`` (a part of ``mesh``) with ``mesh``'s metadata, not the part's parent indices."""
    if out is not mesh:
        out.metadata.update({k: v for k, v in mesh.metadata.items() if k not in ("parent_faces", "parent_vertices")})
        out.metadata.pop("parent_faces", None)
        out.metadata.pop("parent_vertices", None)
    return out


def default_mask_sigma(spacing, step: int = 1) -> float:
    """Default blur σ (physical units) of a binary mask: half the largest voxel side × ``step``.

    A mask has no noise to merge, but its surface is a staircase of voxel faces; blurred by half
    the lateral voxel (:func:`default_sigma`), the terraces of planes 2–3 × farther apart stay, and
    the area of every masked object read 4.5–6 % high in an independent review (shells at 1 × 0.5
    × 0.5 µm, nuclei at 2 × 1 × 1 µm; blurred by half the plane spacing: +0.6 %, radii within
    0.04 µm). The same as :func:`default_sigma` for cubic voxels.
    """
    dz, dy, dx = check_spacing(spacing)
    return 0.5 * max(1, int(step)) * max(dz, dy, dx)


def default_sigma(spacing, step: int = 1) -> float:
    """Default Gaussian blur σ (physical units) for a marching-cubes step of ``step`` voxels.

    Half the lateral sampling distance of the surface, ``step × (dx + dy) / 4``: half a voxel at
    full resolution, one voxel at the paper's step 2. It merges voxel noise (which would make a
    thin wall porous) without pulling the surface towards bright structures near it (every extra
    σ widens the edge), and the surface is only sampled every ``step`` voxels anyway.

    Parameters
    ----------
    spacing : (dz, dy, dx)
        Voxel size.
    step : int
        Marching-cubes step in voxels.

    Returns
    -------
    float
    """
    _, dy, dx = check_spacing(spacing)
    return 0.25 * max(1, int(step)) * (dx + dy)


#: Blurred signal-to-noise ratio :func:`auto_sigma` aims at: (plateau − background) over the
#: noise left after the blur. At 20 the iso-level (half the contrast) lies 10 blurred-noise
#: standard deviations from both plateaus, so a wall of 10⁵–10⁶ surface samples has no hole.
AUTO_SIGMA_SNR = 20.0
#: Largest automatic σ, in lateral sampling distances (``step × (dx + dy) / 2``).
AUTO_SIGMA_MAX_SAMPLES = 3.0
#: Largest automatic σ as a fraction of the object's thickness (``2 × volume / area`` of the
#: thresholded object, an underestimate on porous walls): a blur of 0.4 × a slab's thickness
#: keeps 79 % of its plateau, so the two walls stay apart; the refinement then puts them back
#: on the edges of the lightly blurred image.
AUTO_SIGMA_THICKNESS = 0.4
#: Ratio between the σ of :func:`auto_sigma`'s topology ladder (the default σ × 1.3^k, up to the cap).
AUTO_SIGMA_LADDER = 1.3
#: Lowest Euler characteristic of the thresholded solid (components − tunnels + cavities) that
#: :func:`auto_sigma` accepts as a wall without noise holes: a solid ball is 1, a hollow shell 2,
#: a torus 0; −1 allows a second handle (the surface's χ ≥ −2, as the summary's quality control).
#: Noise makes tunnels through a wall (χ ≪ 0) and bubbles inside it (χ ≫ 0, more than the one
#: lumen per component a shell has): both are refused.
AUTO_SIGMA_MIN_EULER = -1
#: Components of the thresholded sample smaller than this fraction of the largest are specks,
#: left out of the ladder's Euler characteristic (the mesh step drops them as well).
AUTO_SIGMA_SPECK = 0.01
#: Signal-to-noise ratio of the profiles the refinement reads (:func:`reconstruct`, ``refine``):
#: lower than the mesh's, since the shifts are averaged over neighbouring vertices.
REFINE_SNR = 8.0


def blur_noise_gain(sigma: float, spacing) -> float:
    """Factor by which a Gaussian blur of σ (physical) divides white voxel noise's std.

    ``1 / sqrt(∏ Σ_j g_ij²)`` over the three axes, ``g_i`` the normalised discrete kernel of
    σ / d_i voxels (≈ ``sqrt(∏ 2 √π σ / d_i)`` once σ exceeds a voxel; 1 at σ = 0).

    Parameters
    ----------
    sigma : float
        Blur σ in physical units (>= 0).
    spacing : (dz, dy, dx)

    Returns
    -------
    float
        >= 1.
    """
    gain = 1.0
    for d in check_spacing(spacing):
        s = sigma / d
        if s <= 0:
            continue
        x = np.arange(-int(np.ceil(4 * s)) - 1, int(np.ceil(4 * s)) + 2)
        g = np.exp(-0.5 * (x / s) ** 2)
        gain *= float((g / g.sum()) @ (g / g.sum()))
    return float(1.0 / np.sqrt(gain))


def _sigma_for_snr(snr: float | None, spacing, target: float, floor: float, cap: float) -> float:
    """Smallest σ in ``[floor, cap]`` with ``snr × blur_noise_gain(σ) >= target`` (bisection)."""
    cap = max(cap, floor)
    if snr is None or not np.isfinite(snr) or snr * blur_noise_gain(floor, spacing) >= target:
        return floor
    if snr <= 0 or snr * blur_noise_gain(cap, spacing) < target:
        return cap
    lo, hi = floor, cap
    for _ in range(40):  # scalar bisection on a monotone function
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if snr * blur_noise_gain(mid, spacing) < target else (lo, mid)
    return hi


def _object_stats(sample: np.ndarray, blurred: np.ndarray, level: float) -> dict:
    """Background, plateau, noise and contrast of a strided raw sample split by its blurred copy.

    The noise is the larger of the background's spread (:func:`background_spread`, robust to
    clipping, of the raw voxels whose blurred value is below ``level``, :func:`_split_sample`)
    and the object's **dark spread**: how far the raw voxels of the object's core (the
    thresholded blurred sample eroded by one sample, away from its edges) fall below the
    plateau, ``(plateau − 25th percentile) / 0.6745`` (the std of Gaussian noise; 0 when bright
    texture only adds light, as fibres do). Dark gaps inside the object (noise, or speckle such as
    nuclei with dark space between them) make a thresholded wall porous; bright texture does not.
    The plateau is ``2 × level − background`` (the level sits half-way).
    """
    inside, bg, core = _split_sample(sample, blurred, level)
    b, n_bg = background_spread(bg)
    if b is None or core.size < 10:
        return {"background": None, "plateau": None, "noise": None, "snr": None}
    plateau = 2.0 * level - b
    n_dark = max(0.0, plateau - float(np.percentile(core, 25))) / 0.6745
    noise = max(n_bg, n_dark)
    contrast = plateau - b
    return {"background": b, "plateau": plateau, "noise": noise, "background_noise": n_bg, "dark_spread": n_dark,
            "snr": contrast / noise if noise > 0 else None}


def _thickness(inside: np.ndarray, voxel: np.ndarray) -> float | None:
    """Object thickness ``2 V / A`` of a binary sample (voxel size ``voxel``, z, y, x).

    ``A`` from the transitions along each axis: a surface with isotropically distributed normals
    crosses an axis-aligned grid ``A (|n_x| + |n_y| + |n_z|)`` = ``1.5 A`` times per face area,
    so ``A ≈ (2/3) Σ_axes transitions × face area``. A slab of thickness T gives T.
    """
    vol = float(np.count_nonzero(inside)) * float(np.prod(voxel))
    area = 0.0
    for axis in range(3):
        trans = np.count_nonzero(np.diff(inside.view(np.uint8), axis=axis))
        area += trans * float(np.prod(np.delete(voxel, axis)))
    area *= 2.0 / 3.0
    return 2.0 * vol / area if area > 0 and vol > 0 else None


def _solid_euler(inside: np.ndarray) -> tuple[int, int]:
    """(Euler characteristic, components) of a binary solid without its specks (below AUTO_SIGMA_SPECK)."""
    from skimage.measure import euler_number

    labels, n = ndi.label(inside, structure=np.ones((3, 3, 3), bool))
    if n == 0:
        return 0, 0
    sizes = np.bincount(labels.ravel())[1:]
    big = np.concatenate([[False], sizes >= AUTO_SIGMA_SPECK * sizes.max()])
    return int(euler_number(big[labels], connectivity=3)), int(big.sum())


def _hole_excess(chi: int, components: int) -> int:
    """How far χ of a solid lies outside ``[AUTO_SIGMA_MIN_EULER, 2 × components]`` (0: inside)."""
    return max(AUTO_SIGMA_MIN_EULER - chi, chi - 2 * components, 0)


def _topology_sigma(blurred, level_of, floor: float, cap: float) -> tuple[float, list]:
    """Smallest σ of the ladder ``floor × 1.3^k ≤ cap`` whose thresholded solid has no noise holes.

    "No noise holes": the Euler characteristic of the solid (:func:`_solid_euler`) between
    :data:`AUTO_SIGMA_MIN_EULER` and 2 per component (a hollow shell). A noisy wall thresholded at
    too small a σ is full of tunnels (χ ≪ 0) and bubbles (χ ≫ 0), or the threshold catches bright
    texture instead of the wall; all vanish once the blur has averaged the noise. Where the noise made
    the ladder climb and the σ it stops at leaves a tunnel or an opening (χ below 2 per component: a
    torus, a cup, a ball, or the noise's last pore through a shell), the next rung is taken if its χ is
    2 per component in all, with as many components (every one a hollow shell; the sum does not tell a
    cup beside a ball with two voids, nor a solid with a noise void, from that); a z-blurred shell at SNR 3
    kept a pore and was meshed as one wall. A torus's hole, a real pore or a ball's solid stays, and holes
    already there at the default blur (a clean image) are the object's own. When no σ of the ladder reaches the
    range (a truly porous object), the σ closest to it (the smallest among equals).

    ``blurred(σ)`` is the sample blurred by σ, ``level_of(b)`` its iso-level (as reconstruct's).
    Returns σ and the ladder as [(σ, χ, components), ...].
    """
    ladder, accepted = [], None
    sigma = floor
    while sigma <= cap * (1 + 1e-9):  # a handful of blurs of the strided sample
        b = blurred(sigma)
        ladder.append((float(sigma), *_solid_euler(b >= level_of(b))))
        chi, components = ladder[-1][1:]
        if accepted is None and _hole_excess(chi, components) == 0:
            accepted = ladder[-1]
            if chi == 2 * components or sigma == floor:  # shells; or the object's own holes at the default blur
                break
        elif accepted is not None:
            break  # one rung beyond the accepted σ, past the noise's last pore (the ladder records it, taken or not)
        sigma *= AUTO_SIGMA_LADDER
    if accepted is not None:
        # a tunnel or an opening left as the noise's blur rose (a z-blurred wall at SNR 3 kept a pore and was
        # meshed as one wall) closes a rung later where a torus's hole, a real pore or a ball's solid stays;
        # χ is summed over the components, so 2 each is read from the total
        last = ladder[-1]
        shell = last[0] > accepted[0] and last[2] == accepted[2] and last[1] == 2 * last[2]
        return (last if shell else accepted)[0], ladder
    best = min(ladder, key=lambda item: (_hole_excess(*item[1:]), item[0]))
    return best[0], ladder


def auto_sigma(
    volume: np.ndarray,
    spacing,
    step: int = 1,
    *,
    threshold: str | float = "yen",
    target_snr: float = AUTO_SIGMA_SNR,
    max_samples: float = AUTO_SIGMA_MAX_SAMPLES,
    thickness_fraction: float = AUTO_SIGMA_THICKNESS,
) -> tuple[float, dict]:
    """Noise-aware Gaussian blur σ (physical units) for :func:`reconstruct`.

    Rule: the smallest σ, **never below** :func:`default_sigma` (half the lateral sampling
    distance), at which the blurred image's signal-to-noise ratio reaches ``target_snr``::

        SNR(σ) = (plateau − background) / noise × blur_noise_gain(σ),
        blur_noise_gain(σ) ≈ sqrt(∏_i 2 √π σ / d_i)   (white noise, per-axis σ / d_i voxels)

    so anisotropic voxels count: a z-spacing 2.5 × dx averages 2.5 × fewer planes per µm of σ.
    The noise is the larger of the background's spread and the object's dark spread (dark gaps
    inside the object, :func:`_object_stats`); a clean image keeps the default. Then the
    topology check (:func:`_topology_sigma`): σ is raised, if needed, to the smallest step of the
    ladder ``default × 1.3^k`` whose thresholded solid has no noise holes (Euler characteristic
    from −1 to 2 per component). It sees what the spread estimates can miss: an image clipped at 0 (measured: a
    vesicle at SNR 5 whose dark half reads as noise-free) or a threshold caught by bright
    texture instead of the wall. Both rules are capped by ``max_samples`` lateral sampling
    distances (``step × (dx + dy) / 2``); the noise rule also by ``thickness_fraction`` of the
    object's thickness (``2 × volume / area`` of the object thresholded at that σ), so thin walls
    are not blurred away (the topology rule needs no such cap: a wall blurred away changes the
    solid's topology). No cap goes below the default.

    The statistics come from a strided sample of the stack (about :data:`NOISE_SAMPLE_VOXELS`
    voxels) blurred at the default σ and thresholded like :func:`reconstruct` (``edge="half"``).

    Parameters
    ----------
    volume : ndarray, shape (Z, Y, X)
        The raw (unblurred) segmented channel.
    spacing : (dz, dy, dx)
    step : int
        Marching-cubes step (voxels).
    threshold : {"yen", "otsu"} or float
        As in :func:`reconstruct`.
    target_snr : float
        Blurred signal-to-noise ratio to reach (> 0).
    max_samples : float
        Cap in lateral sampling distances (> 0).
    thickness_fraction : float
        Cap as a fraction of the object's thickness (> 0).

    Returns
    -------
    sigma : float
    info : dict
        ``default`` (the floor), ``cap``, ``thickness``, ``background``, ``plateau``, ``noise``
        (with ``background_noise`` and ``dark_spread``), ``snr`` (raw), ``snr_blurred`` (at σ),
        ``limited_by`` (``"default"``, ``"noise"``, ``"topology"`` or ``"cap"``), ``euler_ladder``
        ([(σ, χ of the thresholded solid, its components), ...] of the topology check).

    Raises
    ------
    NemoError
        Bad image or parameters (as :func:`reconstruct`).
    """
    for name, val in (("target_snr", target_snr), ("max_samples", max_samples),
                      ("thickness_fraction", thickness_fraction)):
        if not (isinstance(val, (int, float, np.floating, np.integer)) and np.isfinite(val) and val > 0):
            raise NemoError(f"auto_sigma {name} must be a number > 0, got {val!r}")
    (dz, dy, dx), step, floor = _check_reconstruct_args(spacing, None, "all", "half", step, 0, 0.1)
    source, _, scale, _ = _source(volume, None)
    k = max(1, int(np.ceil((source.size / NOISE_SAMPLE_VOXELS) ** (1 / 3))))
    voxel = np.array([dz, dy, dx]) * k

    cache: dict[float, np.ndarray] = {}

    def blurred(sigma):  # the strided sample blurred by σ (the same σ is asked for more than once)
        if sigma not in cache:
            cache[sigma] = _blur_sampled(source, (sigma / dz, sigma / dy, sigma / dx), k)
        return cache[sigma]

    def level_of(b):  # thresholded like reconstruct (edge "half")
        return _iso_level(b, float(b.min()), float(b.max()), False, threshold, "half", scale,
                          (dz * k, dy * k, dx * k), quiet=True)[0]  # the mesh's own level says how it was found

    b0 = blurred(floor)
    level = level_of(b0)
    sample = np.asarray(source[::k, ::k, ::k], dtype=np.float32)
    stats = _object_stats(sample, b0, level)
    cap = max(floor, max_samples * step * 0.5 * (dx + dy))
    sigma = _sigma_for_snr(stats["snr"], (dz, dy, dx), target_snr, floor, cap)
    thick, sigma_cap = None, cap
    if sigma > floor:  # the thickness of the object seen at that blur caps the noise rule
        b1 = blurred(sigma)  # thresholded like reconstruct would at that σ
        thick = _thickness(b1 >= level_of(b1), voxel)
        if thick is not None:
            sigma_cap = max(floor, min(cap, thickness_fraction * thick))
            sigma = min(sigma, sigma_cap)
    # the topology ladder needs no thickness cap: a wall blurred away changes the solid's topology.
    # On a strided sample (k > 1) each σ is judged at least at the sample's own anti-aliasing blur,
    # so a thin wall missed between the sample points is not counted as a noise hole.
    alias = default_sigma((dz, dy, dx), k)
    sigma_topology, ladder = _topology_sigma(lambda sg: blurred(max(sg, alias)), level_of, floor, cap)
    sigma = max(sigma, sigma_topology)
    snr_b = stats["snr"] * blur_noise_gain(sigma, (dz, dy, dx)) if stats["snr"] is not None else None
    limited = ("default" if sigma <= floor else "topology" if sigma == sigma_topology
               else "cap" if sigma >= sigma_cap else "noise")
    info = {"default": floor, "cap": sigma_cap, "thickness": thick, "snr_blurred": snr_b, "limited_by": limited,
            "euler_ladder": ladder,
            **{key: (val * scale if key in ("background", "plateau", "noise", "background_noise", "dark_spread")
                     and val is not None else val) for key, val in stats.items()}}
    dark = (stats.get("dark_spread") or 0.0) > (stats.get("background_noise") or 0.0)
    # the blur rule's SNR (its noise: the larger of two spreads) is not the frame's QC `snr` (background's spread)
    logger.info("auto sigma %.4g (default %.4g, the blur rule's SNR %s, limited by %s)", sigma, floor,
                "n/a" if stats["snr"] is None else f"{stats['snr']:.3g}" + (
                    " from the object's dark spread: dim voxels inside it, noise or blurred structure" if dark else ""),
                limited)
    return float(sigma), info


def iso_level(volume: np.ndarray, spacing, sigma: float, step: int = 1, threshold: str | float = "yen",
              edge: Literal["half", "threshold", "profile"] = "half") -> float:
    """The iso-level :func:`reconstruct` would mesh ``volume`` at, in its intensity units, before any
    check against the walls' profiles (with ``edge="profile"``: its first pass's, the half level; the
    walls' fitted level needs the mesh; with ``edge="half"`` the check may correct it:
    :func:`checked_half_level`).

    Parameters
    ----------
    volume : ndarray, shape (Z, Y, X)
    spacing : (dz, dy, dx)
    sigma : float
        The blur σ (physical) of the meshed field.
    step : int
        Marching-cubes step (voxels).
    threshold, edge
        As in :func:`reconstruct`.
    """
    (dz, dy, dx), step, sigma = _check_reconstruct_args(spacing, sigma, "all", edge, step, 0, 0.1)
    source, _, scale, _ = _source(volume, None)
    field = _blur_sampled(source, (sigma / dz, sigma / dy, sigma / dx), step)
    level = _iso_level(field, float(field.min()), float(field.max()), False, threshold, edge, scale,
                       (dz * step, dy * step, dx * step))[0]
    return float(level) * scale


def parse_threshold(threshold) -> str | float:
    """``"yen"``, ``"otsu"`` (any case) or a finite number, from a string or a number.

    Raises
    ------
    NemoError
        Anything else.
    """
    if isinstance(threshold, str):
        name = threshold.strip().lower()
        if name in ("yen", "otsu"):
            return name
        try:
            threshold = float(name)
        except ValueError:
            raise NemoError(f"threshold must be 'yen', 'otsu' or a number, got {threshold!r}") from None
    try:
        value = float(threshold)
    except (TypeError, ValueError):
        raise NemoError(f"threshold must be 'yen', 'otsu' or a number, got {threshold!r}") from None
    if not np.isfinite(value):
        raise NemoError(f"threshold must be a finite number, got {threshold!r}")
    return value


def _auto_level(field: np.ndarray, method: str, edge: str, spacing=(1.0, 1.0, 1.0),
                quiet: bool = False) -> tuple[float, float, float | None]:
    """(classification threshold, iso-level, background) of an automatic threshold on a blurred volume.

    The background is the mode of the class below the threshold (None when every or no sample
    lies below it); the plateau the most populated histogram peak above it, moved up to the
    peak of the flat voxels' histogram where that lies on its upper flank
    (:func:`_flat_plateau`); the median of the object's flat core (:func:`_interior_plateau`)
    where that peak lies well below it; without either, the median of the samples above the
    threshold (:func:`_half_level`). The iso-level is half-way between the background and the
    plateau. ``spacing`` (dz, dy, dx) is the physical spacing of ``field``'s samples.
    """
    from skimage import filters

    # the histogram of a strided subsample is indistinguishable from the full one and 10x faster
    k = max(1, int(np.ceil((field.size / _MAX_THRESHOLD_SAMPLES) ** (1 / 3))))
    sub = np.ascontiguousarray(field[::k, ::k, ::k])
    sample = sub.ravel()
    thr = float(filters.threshold_yen(sample) if method == "yen" else filters.threshold_otsu(sample))
    # The two dominant intensity populations of the blurred image: the background (mode of the
    # class below the threshold) and the object plateau (the most populated histogram peak
    # above it). Peaks rather than class medians/modes: robust to the many edge voxels of thin
    # objects, to bright sub-structures (fibres) and to a threshold that cuts through the object.
    edges = _histogram_edges(sample)
    counts, centres = _smoothed_histogram(sample, edges)
    below = centres <= thr
    if below.all() or not below.any():
        return thr, thr, None
    b0 = int(np.argmax(np.where(below, counts, -1.0)))
    background = float(centres[b0])
    if edge == "threshold":
        return thr, thr, background
    level = _half_level(sub, thr, background, method, np.asarray(spacing, float) * k, edges, counts, b0, quiet,
                        flat_top=method == "yen")
    return thr, level, background


def _yen_flat_top(sample: np.ndarray) -> tuple[float, float, float] | None:
    """(middle, lowest, highest) of the thresholds where Yen's criterion on ``sample`` (N,) is flat at its top.

    Yen's criterion (scikit-image's, computed here because ``threshold_yen`` returns only its
    argmax) on a textured tissue with no plateau in its histogram is flat over a wide range: on the
    organoid stack it lies within 0.005 of its best from 508 to 641 counts, so the argmax jumped
    between 445 and 611 as noise was added. The flat top is the bins whose criterion (its log) lies
    within :data:`YEN_FLAT_TOP` of the best (between noise realisations it moves by 0.001–0.003
    there), and its middle is their median (the bins may form several runs: the median can fall between
    two of them, half-way between near-equal candidates). None when the criterion is nowhere finite.
    """
    from skimage.exposure import histogram

    counts, centres = histogram(sample, nbins=256, source_range="image")
    pmf = counts.astype(np.float64) / counts.sum()
    below = np.cumsum(pmf)
    squares_above = np.cumsum(pmf[::-1] ** 2)[::-1]
    with np.errstate(divide="ignore", invalid="ignore"):
        crit = 2.0 * np.log(below[:-1] * (1.0 - below[:-1])) - np.log(np.cumsum(pmf**2)[:-1] * squares_above[1:])
    crit = np.where(np.isfinite(crit), crit, -np.inf)
    if not np.isfinite(crit).any():
        return None
    near = centres[:-1][crit >= crit.max() - YEN_FLAT_TOP]
    return float(np.median(near)), float(near[0]), float(near[-1])


def _half_level(sub: np.ndarray, thr: float, background: float, method: str, spacing: np.ndarray,
                edges: np.ndarray | None = None, counts: np.ndarray | None = None, b0: int | None = None,
                quiet: bool = False, core=..., flat_top: bool = False) -> float:
    """The level half-way between ``background`` and the plateau of the samples ``sub`` above ``thr``
    (:func:`_auto_level`; the histogram of ``sub`` and the background's bin ``b0`` when already made;
    ``core``, :func:`_interior_plateau` of ``sub``, when already found). ``spacing`` is that of
    ``sub``'s samples. Without a plateau the threshold may be the level: then, with ``flat_top``, the middle of
    Yen's flat top (:func:`_yen_flat_top` of ``sub``) stands for ``thr``, the argmax of a flat criterion being a
    coin toss (the organoid's walls read 25 % thicker at one of its two near-equal optima)."""
    sample = sub.ravel()
    above = sample[sample > thr]
    if core is ...:
        core = _interior_plateau(sub, thr, background, float(np.median(above)), spacing) if above.size else None
    if edges is None:
        edges = _histogram_edges(sample)
        counts, _ = _smoothed_histogram(sample, edges)
        b0 = int(np.clip(np.searchsorted(edges, background) - 1, 0, len(counts) - 1))
    # local maxima above the background peak that rise >= 1/3 above the lowest point between
    # the background and them (a prominence test; scipy.signal costs 1 s of import time)
    ext = np.r_[-np.inf, counts, 0.0]  # a plateau in the top bin counts as a peak
    peaks = np.flatnonzero((ext[1:-1] >= ext[:-2]) & (ext[1:-1] > ext[2:]))
    peaks = peaks[peaks > b0]
    valley = np.minimum.accumulate(counts[b0:])  # lowest count from the background peak onwards
    rise = counts[peaks] - valley[peaks - b0]
    # ... and by more than the counts' own noise (3 Poisson std): no blips of the sparse tail
    ok = (counts[peaks] >= (4.0 / 3.0) * valley[peaks - b0]) & (rise >= 3.0 * np.sqrt(counts[peaks]))
    low = None if core is None else core - INTERIOR_MAX_SPREAD * (core - background)
    if core is not None and (not ok.any() or _peak_plateau(sub, background, edges, counts, peaks, ok) < low):
        # an object with a flat core whose histogram peaks well below it: a small object's peaks are
        # its edge voxels (a noisy r 6 µm nucleus: 146 for 168). The plateau is then the core, or
        # the plateau of the most populated peak near it (within INTERIOR_MAX_SPREAD of the contrast)
        # where that is higher. A plateau above the core is not overruled: the "core" of a thin wall
        # under a z-PSF is its caps, which look thick along z but never reach the plateau (a 5 µm
        # wall at σz 2 µm: 160 for the resolved walls' 198), and the plane outside a cap can make a
        # bump in the skirt (38) that outnumbers the plateau's peaks near the core
        near = ok & (edges[peaks + 1] >= low) & (edges[peaks] <= 2.0 * core - low)
        plateau = max(core, _peak_plateau(sub, background, edges, counts, peaks, near) if near.any() else core)
        return max(thr, 0.5 * (background + plateau))
    if not ok.any():  # no plateau peak (a blob, or a wall smeared by texture and noise)
        # half-way to the object's median, never below the threshold: a textured noisy wall gets
        # its half-maximum level, a blob (median near the threshold) the threshold
        threshold_argmax = thr
        flat_top = _yen_flat_top(sample) if flat_top else None
        if flat_top is not None:
            thr = flat_top[0]
            above = sample[sample > thr]
        if not above.size:
            return thr
        level = max(thr, 0.5 * (background + float(np.median(above))))
        if not quiet:
            where = "half-way to the object's median" if level != thr else (
                f"at the {method} threshold" if flat_top is None else f"at the middle of Yen's flat criterion, "
                f"{flat_top[0]:.4g} ({flat_top[1]:.4g} to {flat_top[2]:.4g}; its argmax, the classification threshold, "
                f"{threshold_argmax:.4g})")
            logger.info("no object plateau in the intensity histogram: surface %s", where)
        return level
    return 0.5 * (background + _peak_plateau(sub, background, edges, counts, peaks, ok))


def _peak_plateau(sub: np.ndarray, background: float, edges: np.ndarray, counts: np.ndarray, peaks: np.ndarray,
                  ok: np.ndarray) -> float:
    """The plateau of the histogram's most populated accepted peak (:func:`_flat_plateau`)."""
    return _flat_plateau(sub, background, edges, counts, peaks[ok][np.argmax(counts[peaks[ok]])])


def _interior_plateau(sub: np.ndarray, thr: float, background: float, median: float,
                      spacing: np.ndarray, per_axis: bool = False) -> float | None:
    """The plateau of an object's flat core, or None when it has none.

    A small object (a droplet or a nucleus a few voxels across) has too few voxels for a plateau
    peak in the histogram once noise spreads them, and most of its voxels lie on the blurred
    edge, so its median is well below the plateau (a noisy ball of radius 6 voxels: level 719 for
    900, volume +13 %). Its core is the plateau. Depths are counted in edge widths σ inside the
    threshold surface (Euclidean distance, physical), σ measured as
    ``(median − background) / (√(2π) g)``, g the median gradient magnitude within 10 % of the
    contrast of the provisional half level (an erf edge of contrast C and width σ is steepest at
    C / (√(2π) σ)). The interior lies deeper than :data:`INTERIOR_EDGE_WIDTHS` σ, its core one σ
    deeper still; the plateau is the core's median. Accepted only for a flat interior: at least
    :data:`INTERIOR_MIN_SAMPLES` samples in the core (twice that in the interior), and both the
    interior's spread (interquartile range / 1.349) and the core's step over the interior's
    first σ at most :data:`INTERIOR_MAX_SPREAD` of the contrast. A wall's texture fails it: a
    bright sheet in a wall fills a thin interior with no core, fibres make a step or a spread.

    Parameters
    ----------
    sub : ndarray, shape (Z, Y, X)
        The (strided) blurred volume.
    thr : float
        The classification threshold.
    background, median : float
        The background and the median of the samples above ``thr``.
    spacing : ndarray, shape (3,)
        Physical spacing of ``sub``'s samples (dz, dy, dx).
    per_axis : bool
        Count depths in each axis's own edge width (:func:`_edge_width`): under a z-elongated PSF a
        wall's poles are blurred deeper than its sides, and the lower threshold's region around them
        is thick enough to hold a "core" of the dimmed crest (a 6 µm wall under σz 2 µm read a plateau
        0.9 × its own; an independent review). :func:`_own_level` uses it.
    """
    if min(sub.shape) < 3 or median <= background:
        return None
    labels, n = ndi.label(sub > thr)  # the objects' bounding box (no speck of noise), a sample around it
    if not n:
        return None
    sizes = np.bincount(labels.ravel(), minlength=n + 1)[1:]
    box = ndi.find_objects(np.isin(labels, np.flatnonzero(sizes >= 0.01 * sizes.max()) + 1).astype(np.int8))[0]
    sub = sub[tuple(slice(max(0, b.start - 1), b.stop + 1) for b in box)]
    (sub,), spacing = _interior_sample([sub], spacing)
    width = _edge_width(sub, background, median, spacing, per_axis=per_axis)
    if width is None:
        return None
    depth = ndi.distance_transform_edt(sub > thr, sampling=spacing / width)  # in edge widths
    inside = sub[depth > INTERIOR_EDGE_WIDTHS]
    core = sub[depth > INTERIOR_EDGE_WIDTHS + 1.0]
    if inside.size < 2 * INTERIOR_MIN_SAMPLES or core.size < INTERIOR_MIN_SAMPLES:
        return None
    q25, q75 = np.percentile(inside, [25, 75])
    first = (depth > INTERIOR_EDGE_WIDTHS) & (depth <= INTERIOR_EDGE_WIDTHS + 1.0)  # the interior's first σ
    plateau = float(np.median(core))
    step = abs(plateau - float(np.median(sub[first]))) if first.any() else 0.0  # none in it (a coarse grid): the spread
    flat = max((q75 - q25) / 1.349, step) <= INTERIOR_MAX_SPREAD * (plateau - background)
    return plateau if plateau > median and flat else None


def _edge_width(sub: np.ndarray, background: float, median: float, spacing: np.ndarray,
                per_axis: bool = False) -> float | np.ndarray | None:
    """The width σ of an object's blurred edge, ``(median − background) / (√(2π) g)`` with g the
    median gradient magnitude within 10 % of the contrast of the provisional half level (an erf edge
    of contrast C and width σ is steepest at C / (√(2π) σ)); None without samples there.
    ``per_axis``: σ along each axis (3,) z, y, x, from the samples whose gradient lies within 26° of
    that axis (|g_axis| ≥ 0.9 |g|), the overall σ for an axis with fewer than
    :data:`INTERIOR_MIN_SAMPLES` such samples."""
    half = 0.5 * (background + median)
    band = np.abs(sub - half) < 0.1 * (median - background)
    if not band.any():
        return None
    parts = [g[band] / d for g, d in zip(np.gradient(sub.astype(np.float32, copy=False)), spacing)]
    magnitude = np.sqrt(sum(g**2 for g in parts))

    def width(where: np.ndarray | slice) -> float:
        return (median - background) / (np.sqrt(2.0 * np.pi) * max(float(np.median(magnitude[where])), 1e-300))

    if not per_axis:
        return width(slice(None))
    along = [np.abs(g) >= 0.9 * magnitude for g in parts]
    return np.array([width(a) if a.sum() >= INTERIOR_MIN_SAMPLES else width(slice(None)) for a in along])


def _object_levels(field: np.ndarray, thr: float, background: float | None, level: float, method: str,
                   spacing: np.ndarray, shift: bool = True) -> tuple[list[float], list[list[float]], np.ndarray | None]:
    """Shift ``field`` (in place) so that each separate bright object crosses ``level`` at its own half level.

    One level for the whole stack puts a dim object's surface inside it, or loses it, next to a
    bright one (nuclei of 0.4–1 × the brightest: −85 % to −18 % in volume, two lost, in an
    independent review). Each object region (:func:`_object_regions`) gets its own level
    (:func:`_own_level`, in its bounding box with the other regions replaced by the background);
    where one differs from ``level`` by more than :data:`OBJECT_LEVEL_TOLERANCE` of the
    contrast, the field over the regions and two samples around them is shifted by ``level``
    minus their level (a higher level wins where two meet). The regions lie above the lower of the
    threshold and ``level``, so each holds its whole edge: an automatic threshold above the stack's
    level (noise: Yen's picked the brighter objects among dim ones) would cut them inside their
    edges and miss the dim ones. ``shift=False`` (the refinement, which crosses the stack's one
    level, or ``edge="threshold"``): the peaks only, the field left as it is.

    Returns
    -------
    levels : list of float
        The objects' levels (largest region first) when the field was shifted, else empty.
    peaks : list of [x, y, z]
        The brightest sample of each compact region (:func:`_compact`; physical units,
        ``spacing`` the samples' spacing) when there are at least two regions, else empty:
        :func:`regions_per_object` counts them per object, so that blobs the mesh joined into
        one surface are told (the parts of a textured wall that the component tree parts are
        not compact).
    offsets : ndarray of float32, the shape of ``field``, or None
        What was subtracted from ``field`` (each object's level minus ``level``) when it was shifted.
    """
    if background is None or level <= background:
        return [], [], None
    thr = min(thr, level)
    regions = _object_regions(field, thr, level, spacing)
    if len(regions) < 2:
        return [], [], None
    levels, peaks = [], []
    for sl, own, others, wide in regions:  # a loop over the few objects
        region = np.where(others, np.float32(background), field[sl])
        if shift:
            levels.append(_own_level(region, own, thr, background, level, method, spacing))
        if not wide and _compact(region, own, thr, spacing):  # a nucleus, not a piece of a wall or of a nucleus
            peak = np.unravel_index(int(np.argmax(np.where(own, region, -np.inf))), own.shape)
            peaks.append([float((b.start + i) * d) for b, i, d in zip(sl, peak, spacing)][::-1])  # x, y, z
    if not shift or max(abs(lev - level) for lev in levels) <= OBJECT_LEVEL_TOLERANCE * (level - background):
        return [], peaks, None
    offsets = np.zeros(field.shape, dtype=np.float32)  # the one full-size temporary
    for j in np.argsort(levels, kind="stable"):  # ascending: a higher level wins where zones meet
        sl, own = regions[j][:2]
        offsets[sl][ndi.binary_dilation(own, iterations=2)] = levels[j] - level
    _subtract_by_slabs(field, offsets)
    return [float(lev) for lev in levels], peaks, offsets


def _subtract_by_slabs(field: np.ndarray, offsets: np.ndarray, factor: float = 1.0) -> None:
    """``field -= factor × offsets`` in place, over slabs of planes (no full-size temporary)."""
    slab = max(1, _SLAB_VOXELS // max(1, field[0].size))
    for z in range(0, len(field), slab):  # a loop over slabs of planes
        field[z:z + slab] -= np.float32(factor) * offsets[z:z + slab]


def _cores(own: np.ndarray, crop: np.ndarray, thr: float, least: float) -> tuple[np.ndarray, np.ndarray]:
    """(labelled cores, their labels) of a region: the leaves of its component tree over seven rungs
    between ``thr`` and its 99th percentile (parts of at least ``least`` samples; each part split
    again at higher rungs). Two nuclei joined above the stack's level by the light between them
    part higher up, a dim one below a bright one's level part lower down. More than
    :data:`OBJECT_LEVEL_MAX_PARTS` leaves are the texture of one object (a wall's fibres): no split."""
    rungs = np.linspace(thr, float(np.percentile(crop[own], 99)), 9)[1:-1]
    leaves = _leaves(own, crop, rungs, least)
    if not 2 <= len(leaves) <= OBJECT_LEVEL_MAX_PARTS:
        return own.astype(np.int32), np.zeros(0, dtype=np.int64)
    cores = np.zeros(own.shape, dtype=np.int32)
    for label, leaf in enumerate(leaves, start=1):  # a loop over the few objects
        cores[leaf] = label
    return cores, np.arange(1, len(leaves) + 1)


def _leaves(part: np.ndarray, crop: np.ndarray, rungs: np.ndarray, least: float) -> list[np.ndarray]:
    """The parts of ``part`` that split off at the lowest of ``rungs`` that splits it, each split again
    at the rungs above (recursion depth at most the rungs); ``[part]`` when none does."""
    for i, rung in enumerate(rungs):
        labels, n = ndi.label(part & (crop > rung))
        kept = np.flatnonzero(np.bincount(labels.ravel(), minlength=n + 1)[1:] >= least) + 1
        if len(kept) > OBJECT_LEVEL_MAX_PARTS:
            return [part] * (OBJECT_LEVEL_MAX_PARTS + 1)  # texture: too many to be objects
        if len(kept) >= 2:
            return [leaf for k in kept for leaf in _leaves(labels == k, crop, rungs[i + 1:], least)]
    return [part]


def _own_level(region: np.ndarray, own: np.ndarray, thr: float, background: float, level: float, method: str,
               spacing: np.ndarray) -> float:
    """An object's own half level: half-way to its flat core (:func:`_interior_plateau`); without one,
    half-way to a compact object's top (:func:`_deep_plateau`); else its half level
    (:func:`_half_level`) if it lies wholly below the stack's ``level`` (it would be lost), else
    ``level``: a thin wall never reaches its plateau, and its own histogram reads low (a 4-voxel
    shell beside a ball of the same brightness came out 0.3 voxel thicker)."""
    values = region[own]
    median = float(np.median(values[values > thr])) if np.any(values > thr) else thr
    core = _interior_plateau(region, thr, background, median, spacing, per_axis=True)
    if core is not None:
        return max(thr, 0.5 * (background + core))
    top = _deep_plateau(region, own, thr, background, median, spacing)
    if top is not None:  # a small compact object: half-way to its top
        return max(thr, 0.5 * (background + top))
    if float(values.max()) <= level:
        return max(thr, _half_level(region, thr, background, method, spacing, quiet=True, core=None))
    return level


def _interior_sample(arrays: list[np.ndarray], spacing: np.ndarray) -> tuple[list[np.ndarray], np.ndarray]:
    """``arrays`` (one shape) strided to at most :data:`_MAX_INTERIOR_SAMPLES` samples, and their
    spacing: the distance transforms of :func:`_interior_plateau` and :func:`_deep_plateau` cost
    0.6 s at 1.6 M samples (a shell of 200³ is read every third sample)."""
    m = max(1, int(np.ceil((arrays[0].size / _MAX_INTERIOR_SAMPLES) ** (1 / 3))))
    return [a[::m, ::m, ::m] for a in arrays], spacing * m


def _compact(region: np.ndarray, own: np.ndarray, thr: float, spacing: np.ndarray) -> bool:
    """Whether a region is a blob: its greatest depth inside ``thr`` is at least
    :data:`BLOB_MIN_DEPTH` × the radius of a ball of its volume (a wall or a sheet is not), read
    on a strided sample as :func:`_deep_plateau` does."""
    (region, own), spacing = _interior_sample([region, own], spacing)
    inside = own & (region > thr)
    n = int(inside.sum())
    if n < INTERIOR_MIN_SAMPLES:
        return False
    deepest = float(ndi.distance_transform_edt(inside, sampling=spacing).max())
    return deepest >= BLOB_MIN_DEPTH * (3.0 * n * float(np.prod(spacing)) / (4.0 * np.pi)) ** (1 / 3)


def _deep_plateau(region: np.ndarray, own: np.ndarray, thr: float, background: float, median: float,
                  spacing: np.ndarray) -> float | None:
    """The plateau of a compact object without a flat core: the median of its samples at least
    half its greatest depth inside (a blob's top). None for a wall or sheet (greatest depth below
    :data:`BLOB_MIN_DEPTH` × the radius of a ball of its volume: it is thin, and its own top reads
    low, so it keeps the stack's level) and for an object whose greatest depth is below
    :data:`BLOB_MIN_WIDTHS` edge widths (:func:`_edge_width`): blurred that much, its top would be
    well below its plateau.

    Small nuclei (radius 3–4 µm at 2 µm planes) have no interior deeper than a few edge widths, so
    no flat core (:func:`_interior_plateau`); they kept the stack's level, far below theirs in a
    tissue of nuclei of 0.5–1 × the brightest (an independent review: 79 of 200 nuclei, volume
    +18 % median, up to +50 %). Depths are physical (``spacing``), inside the object's half maximum:
    half-way from the background to a first top (the median of the samples at least half the
    greatest depth inside ``thr``, which reaches far into the blur: read there, a ball of radius
    2 σ beside two larger ones took level 47 for 100, volume +50 %; now 68.5, −17 %, and the
    stack's 100 gives −63 %). A large region is read on a strided sample (at most
    :data:`_MAX_INTERIOR_SAMPLES`), as :func:`_interior_plateau` does.
    """
    (region, own), spacing = _interior_sample([region, own], spacing)
    inside = own & (region > thr)
    if inside.sum() < INTERIOR_MIN_SAMPLES:
        return None
    depth = ndi.distance_transform_edt(inside, sampling=spacing)
    peak = float(np.median(region[inside & (depth >= 0.5 * float(depth.max()))]))  # the top, roughly
    inside = own & (region > max(thr, 0.5 * (background + peak)))
    n = int(inside.sum())
    if n < INTERIOR_MIN_SAMPLES:
        return None
    depth = ndi.distance_transform_edt(inside, sampling=spacing)
    deepest = float(depth.max())
    if deepest < BLOB_MIN_DEPTH * (3.0 * n * float(np.prod(spacing)) / (4.0 * np.pi)) ** (1 / 3):
        return None
    width = _edge_width(region, background, median, spacing)
    if width is None or deepest < BLOB_MIN_WIDTHS * width:
        return None
    return float(np.median(region[inside & (depth >= 0.5 * deepest)]))


def _object_regions(field: np.ndarray, thr: float, level: float,
                    spacing: np.ndarray | None = None) -> list[tuple[tuple, np.ndarray, np.ndarray, bool]]:
    """The separate objects of a blurred field: (bounding slices with 3 samples around, its samples,
    the other objects' samples, whether it meets another part of its region over a wide face),
    largest first.

    An object is a connected region above ``thr`` with at least :data:`OBJECT_LEVEL_MIN_SAMPLES`
    samples and :data:`OBJECT_LEVEL_MIN_FRACTION` of the largest one's. Nuclei a micrometre apart
    are one region above a low threshold: a region that holds several such cores (:func:`_cores`)
    is split between them by a watershed of the field (scikit-image). Two nuclei meet over a
    neck; two bright foci of one nucleus split it across its middle, over a face as wide as the
    part (:func:`_wide_face`, with ``spacing`` the samples' spacing): such a part is not a blob of
    its own.
    """
    from skimage.segmentation import watershed

    labels, n = ndi.label(field > thr)
    if n == 0:
        return []
    sizes = np.bincount(labels.ravel(), minlength=n + 1)[1:]
    least = max(OBJECT_LEVEL_MIN_SAMPLES, OBJECT_LEVEL_MIN_FRACTION * sizes.max())
    boxes = ndi.find_objects(labels)
    regions = []
    for k in np.flatnonzero(sizes >= least):  # a loop over the few objects
        sl = tuple(slice(max(0, b.start - 3), min(m, b.stop + 3)) for b, m in zip(boxes[k], field.shape))
        own, crop = labels[sl] == k + 1, field[sl]
        cores, kept = _cores(own, crop, thr, least)
        if len(kept) < 2:
            regions.append((sl, own, (labels[sl] != 0) & ~own, False))
            continue
        split = watershed(-crop, np.where(np.isin(cores, kept), cores, 0), mask=own)
        for c in kept:
            part = split == c
            regions.append((sl, part, (labels[sl] != 0) & ~part, _wide_face(split, c, spacing)))
    regions.sort(key=lambda r: -int(r[1].sum()))
    return regions


def _wide_face(split: np.ndarray, label: int, spacing: np.ndarray | None) -> bool:
    """Whether part ``label`` of a watershed ``split`` meets the region's other parts over a face at
    least :data:`NECK_MAX_FRACTION` of the cross-section π r² of a ball of its volume.

    Two touching nuclei blurred together meet over a neck; a nucleus split between two bright foci
    (chromocentres) is cut across its middle, its widest section (an independent review: a
    nucleus with two foci was flagged as two nuclei meshed as one)."""
    spacing = np.ones(3) if spacing is None else np.asarray(spacing, dtype=np.float64)
    own = split == label
    other = (split > 0) & ~own
    face = 0.0
    for axis in range(3):  # a loop over the three axes
        a, b = (np.take(m, np.arange(m.shape[axis] - 1), axis=axis) for m in (own, other))
        a2, b2 = (np.take(m, np.arange(1, m.shape[axis]), axis=axis) for m in (own, other))
        face += float(np.count_nonzero((a & b2) | (b & a2))) * float(np.prod(np.delete(spacing, axis)))
    radius = (3.0 * np.count_nonzero(own) * float(np.prod(spacing)) / (4.0 * np.pi)) ** (1 / 3)
    return face >= NECK_MAX_FRACTION * np.pi * radius**2


def _histogram_edges(values: np.ndarray, bins: int = 256) -> np.ndarray:
    """Edges of ``bins`` equal bins over the values' range; for integer values (an unblurred
    8-bit image, ``sigma`` 0) whole numbers of levels per bin, centred on the levels.

    Equal bins over a range of fewer than ``bins`` integer levels alternate between holding one
    level and none, and that comb's teeth read as histogram peaks: an unblurred 8-bit shell
    (background 10, plateau 50) got a plateau just above the background and a level of 10.5.
    """
    lo, hi = float(values.min()), float(values.max())
    if not np.array_equal(values, np.round(values)):
        return np.linspace(lo, hi, bins + 1)
    width = max(1.0, np.ceil((hi - lo + 1.0) / bins))
    return lo - 0.5 + width * np.arange(int(np.ceil((hi - lo + 1.0) / width)) + 1)


def _smoothed_histogram(values: np.ndarray, edges: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Counts in the bins of ``edges`` (:func:`_histogram_edges`), smoothed by one bin, and the
    bins' centres."""
    counts, _ = np.histogram(values, bins=edges)
    return ndi.gaussian_filter1d(counts.astype(np.float64), 1.0), 0.5 * (edges[1:] + edges[:-1])


def _flat_plateau(sub: np.ndarray, background: float, edges: np.ndarray, counts: np.ndarray, top: int) -> float:
    """The object's plateau: the histogram peak of its flat voxels where it lies on the upper
    flank of the whole histogram's peak (bin ``top``), else that peak.

    Noise smears the plateau's spike of well-resolved voxels into the continuum of partial-volume
    edge voxels below it, and the whole histogram's peak slides down (an 8-bit shell at SNR 10:
    187 for 200, its walls 0.3 µm outward). Voxels above the half level where the blurred image
    is flat (gradient below :data:`FLAT_GRADIENT` × the median gradient at the edge, the voxels
    within 10 % of the contrast of the half level) are off the edge: their histogram keeps the
    plateau without the continuum (196 for 200). It is used between ``peak`` and the upper
    half-height of the whole histogram's peak, and fades out from there to its quarter-height
    (a hard cut made a time-lapse's level jump by 4 % of the contrast between identical frames):
    a textured wall whose flat voxels are its dim gaps or its bright tops (a tissue's nuclei)
    keeps ``peak``.

    Parameters
    ----------
    sub : ndarray, shape (Z, Y, X)
        The (strided) blurred volume.
    background : float
        Its background intensity (:func:`_auto_level`).
    edges : ndarray, shape (B + 1,)
        The histogram's bin edges (:func:`_histogram_edges`).
    counts : ndarray, shape (B,)
        Its smoothed histogram (:func:`_smoothed_histogram`).
    top : int
        The bin of the whole histogram's plateau peak.

    Returns
    -------
    float
        The plateau intensity.
    """
    peak = 0.5 * float(edges[top] + edges[top + 1])
    if min(sub.shape) < 2:  # no gradient across a single plane
        return peak
    half = 0.5 * (background + peak)
    grad = np.sqrt(sum(g * g for g in np.gradient(sub.astype(np.float32, copy=False))))
    band = np.abs(sub - half) < 0.1 * (peak - background)
    if not band.any():
        return peak
    flat = sub[(grad < FLAT_GRADIENT * np.median(grad[band])) & (sub > half)]
    if not flat.size:
        return peak
    flat_top = int(np.argmax(_smoothed_histogram(flat, edges)[0]))
    if flat_top < top:
        return peak
    # from the upper half-height to the quarter-height its weight fades: no jump where it is crossed
    half_height, quarter_height = (top + _first(counts[top:] < f * counts[top], len(counts)) for f in (0.5, 0.25))
    weight = float(np.clip((quarter_height - flat_top) / max(quarter_height - half_height, 1), 0.0, 1.0))
    return weight * 0.5 * float(edges[flat_top] + edges[flat_top + 1]) + (1.0 - weight) * peak


def _first(flags: np.ndarray, default: int) -> int:
    """Index of the first True in ``flags`` (``default`` when none)."""
    hit = np.flatnonzero(flags)
    return int(hit[0]) if hit.size else default


def _cancel_duplicate_faces(faces: np.ndarray) -> np.ndarray:
    """Remove faces repeated on the same three vertices, cancelling opposite windings.

    Merging coincident marching-cubes vertices turns two sheets that touch at the iso-level
    into back-to-back face pairs (a membrane of zero thickness whose normals cancel). Per
    vertex triple the windings are summed (+1 / −1); a net of 0 removes every copy, otherwise
    one face of the net winding is kept.
    """
    if len(faces) == 0:
        return faces
    order = np.argsort(faces, axis=1)
    key = np.take_along_axis(faces, order, axis=1)
    n = int(key.max()) + 1
    if n < 2_000_000:  # one int64 per triple (n³ < 2⁶³): a 1-D sort, 5x faster than unique(axis=0)
        key = (key[:, 0] * n + key[:, 1]) * n + key[:, 2]
        srt = np.sort(key)
        if not (srt[1:] == srt[:-1]).any():
            return faces
    # winding relative to the sorted triple: cyclic shifts of (0, 1, 2) are +1, the rest -1
    parity = np.where(((order[:, 1] - order[:, 0]) % 3) == 1, 1, -1)
    _, inverse = np.unique(key, axis=0 if key.ndim == 2 else None, return_inverse=True)
    inverse = inverse.ravel()
    net = np.bincount(inverse, weights=parity).astype(np.int64)
    # keep, per triple with net != 0, the first face whose winding is the net's sign
    cand = np.flatnonzero(parity == np.sign(net[inverse]))
    keep_idx = np.full(len(net), -1, dtype=np.int64)
    keep_idx[inverse[cand[::-1]]] = cand[::-1]  # last write wins -> the first candidate
    keep_idx = keep_idx[(net != 0) & (keep_idx >= 0)]
    logger.debug("removed %d duplicate/back-to-back faces", len(faces) - len(keep_idx))
    return faces[np.sort(keep_idx)]


def _check_finite(volume: np.ndarray) -> None:
    """Raise :class:`NemoError` if a float volume holds NaN or infinite voxels (slab by slab:
    no full-size temporary)."""
    if not np.issubdtype(volume.dtype, np.inexact):
        return
    slab = max(1, 8_000_000 // max(1, volume[0].size))
    bad = sum(int(np.count_nonzero(~np.isfinite(volume[z:z + slab]))) for z in range(0, len(volume), slab))
    if bad:
        raise NemoError(
            f"the image has {bad} NaN or infinite voxels ({100 * bad / volume.size:.2g} % of it): "
            "replace them (e.g. by the background intensity) before meshing, or give a `mask`"
        )


def _float32_safe(volume: np.ndarray) -> tuple[np.ndarray, float]:
    """The volume (float images: finite, rescaled if needed) and the factor it was divided by.

    The blur runs in float32: a float64 image whose largest |value| is above
    :data:`_FLOAT32_SAFE` (up to 1.8e308, float32 ends at 3.4e38) would overflow to infinity, one
    below it would lose its contrast to float32 underflow. Such an image is divided by its largest
    |value| slab by slab into a float32 copy; the iso-level is relative, so the surface is the
    same as that of the image scaled down (a numeric threshold is divided by the same factor).
    A constant image (e.g. all zeros) raises :class:`NemoError`.
    """
    _check_finite(volume)
    vmin, vmax = volume.min(), volume.max()
    if vmin == vmax:
        raise NemoError(
            f"the image is constant (every voxel = {float(vmin):g}, e.g. an all-dark stack): no object to "
            "threshold; check the time point/channel and the file, or give a `mask`"
        )
    if not np.issubdtype(volume.dtype, np.floating):
        return volume, 1.0
    scale = max(abs(float(vmin)), abs(float(vmax)))
    if _FLOAT32_SAFE[0] <= scale <= _FLOAT32_SAFE[1]:
        return volume, 1.0
    logger.info("intensities up to %.4g: dividing by it before the float32 blur", scale)
    out = np.empty(volume.shape, dtype=np.float32)
    slab = max(1, 8_000_000 // max(1, volume[0].size))
    for z in range(0, len(volume), slab):
        np.divide(volume[z:z + slab], scale, out=out[z:z + slab], casting="unsafe")
    return out, scale


def _blur_sampled(src: np.ndarray, sig_vox: tuple[float, float, float], step: int, truncate: float = 3.0) -> np.ndarray:
    """Gaussian blur (float32) sampled at every ``step``-th voxel along each axis.

    The separable filter runs axis by axis and each axis is subsampled right after its pass,
    so later passes touch 1/step, 1/step² of the voxels; the result equals
    ``gaussian_filter(src)[::step, ::step, ::step]`` exactly (up to float rounding).

    Returns
    -------
    ndarray, shape (ceil(Z/step), ceil(Y/step), ceil(X/step)), float32, C-contiguous
    """
    out = _first_pass(src, sig_vox[2], step, truncate) if step > 1 else src
    for axis in (2, 1, 0) if step == 1 else (1, 0):
        if sig_vox[axis] > 0:
            out = ndi.gaussian_filter1d(out, sig_vox[axis], axis=axis, output=np.float32, truncate=truncate)
        if step > 1:
            index = [slice(None)] * 3
            index[axis] = slice(None, None, step)
            out = out[tuple(index)]
    return np.ascontiguousarray(out, dtype=np.float32)


#: Voxels per slab of planes in :func:`_first_pass` (32 MB of float32).
_SLAB_VOXELS = 8_000_000


def _first_pass(src: np.ndarray, sigma_x: float, step: int, truncate: float) -> np.ndarray:
    """The blur along x of ``src`` (Z, Y, X), sampled at every ``step``-th column, slab by slab of
    planes: the full-size float32 intermediate (and its page faults: 0.7 s of a 450³ stack) is
    never made. Each row is filtered whole, so the result is that of the whole stack's pass."""
    if sigma_x <= 0:  # nothing to filter along x: sampled as it is (its type kept for the next pass)
        return src[:, :, ::step]
    out = np.empty(src.shape[:2] + (len(range(0, src.shape[2], step)),), np.float32)
    slab = max(1, _SLAB_VOXELS // max(1, src[0].size))
    for z in range(0, len(src), slab):  # a loop over slabs of planes
        part = ndi.gaussian_filter1d(src[z:z + slab], sigma_x, axis=2, output=np.float32, truncate=truncate)
        out[z:z + slab] = part[:, :, ::step]
    return out


def _taubin(vertices: np.ndarray, faces: np.ndarray, n_iter: int, pass_band: float) -> np.ndarray:
    """Windowed-sinc (Taubin) smoothing via VTK; returns new vertex positions (N, 3)."""
    import pyvista as pv

    poly = pv.PolyData.from_regular_faces(vertices, faces)
    out = poly.smooth_taubin(n_iter=int(n_iter), pass_band=float(pass_band), normalize_coordinates=True,
                             boundary_smoothing=False, non_manifold_smoothing=True)
    points = np.asarray(out.points, dtype=np.float64)
    if points.shape != vertices.shape:  # VTK never drops points here; guard against surprises
        raise RuntimeError("Taubin smoothing changed the number of vertices")
    return points


# --------------------------------------------------------------------------- reconstruct
def reconstruct(
    volume: np.ndarray | None,
    spacing: tuple[float, float, float],
    sigma: float | None = None,
    threshold: str | float = "yen",
    mask: np.ndarray | None = None,
    step: int = 1,
    smooth_iter: int = 10,
    keep: Literal["largest", "all"] = "largest",
    edge: Literal["half", "threshold", "profile"] = "half",
    unit: str = "um",
    pass_band: float = 0.1,
    border: Literal["open", "closed"] = "open",
    refine: bool = False,
    refine_sigma: float | None = None,
    refine_to: Literal["level", "steepest"] | None = "level",
    level_offsets: np.ndarray | None = None,
) -> trimesh.Trimesh:
    """Reconstruct the surface of the bright object(s) in a 3-D image as a triangle mesh.

    Parameters
    ----------
    volume : ndarray, shape (Z, Y, X)
        The image (any real dtype). May be ``None`` when ``mask`` is given.
    spacing : (dz, dy, dx)
        Voxel size in ``unit`` (µm).
    sigma : float, optional
        Gaussian blur σ in physical units (per-axis σ/spacing voxels). Default
        :func:`default_sigma`: ``step × (dx + dy) / 4``, half the surface sampling distance
        (half a voxel at step 1, one voxel at step 2). ``0`` = no blur.
    threshold : {"yen", "otsu"} or float
        Automatic threshold on the blurred image, or an iso-level in the image's intensity
        units. Ignored when ``mask`` is given.
    mask : ndarray of bool, shape (Z, Y, X), optional
        A binary mask of the object to use instead of thresholding (blurred by σ and cut at
        0.5, which gives a smooth sub-voxel surface).
    step : int
        Marching-cubes step in voxels (1 = full resolution; 2 halves the edge length and
        quarters the number of faces).
    smooth_iter : int
        Taubin (windowed-sinc, non-shrinking) smoothing iterations; 0 = none.
    keep : {"largest", "all"}
        Keep the largest connected component (by area) or every component.
    edge : {"half", "threshold", "profile"}
        For automatic thresholds: place the surface half-way between the background and the
        object's plateau intensity (module docstring) (``"half"``, the true position of a blurred
        edge), at the automatic threshold itself (``"threshold"``), or (``"profile"``) mesh at the
        half level first and again at the level that blurred boxes fitted to the walls' intensity
        along its normals imply (:func:`nemo.refine.wall_profile_level`: a thin z-blurred wall that
        never reaches its plateau, or noise clipped at the detector's range, moves the histogram's
        half level, not the fitted boxes'; recorded as ``metadata["nemo_surface"]["profile"]``).
    unit : str
        Unit of ``spacing`` (stored in ``mesh.units``).
    pass_band : float
        Pass band of the windowed-sinc filter (0 < pass_band < 2; lower = smoother).
    border : {"open", "closed"}
        An object cut by the edge of the image: ``"open"`` (default) removes the flat cap that
        closes it along the border planes, leaving an open surface whose rim lies on the border
        (no fake geometry); ``"closed"`` keeps the capped, closed surface. An object inside the
        field has no cap: both give the same surface.
    refine : bool
        Sub-voxel refinement (:mod:`nemo.refine`, default off: on noisy anisotropic images it
        roughens the wall, docs/validation.md): after the smoothing, every vertex
        moves along its normal to the edge of the lightly blurred image (``refine_to``: its
        iso-level crossing or its steepest point; at most 1.5 samples, shifts regularised over
        neighbours), undoing the pull of the mesh blur
        and the marching-cubes step. Vertices on the image border stay. Skipped for a ``mask``
        (a binary mask has no sub-voxel edge: its blurred 0.5 level already is the surface).
    refine_sigma : float, optional
        Blur σ (physical) of the image the refinement reads. Default: none for a clean image,
        else the smallest σ giving the profiles a signal-to-noise ratio of :data:`REFINE_SNR`
        (:func:`blur_noise_gain`), at most ``sigma``.
    refine_to : {"level", "steepest"} or None
        The edge the refinement moves to (None: ``"level"``): where the profile crosses the iso-level (``"level"``),
        or where the profile (averaged over neighbouring vertices) falls most steeply between
        the background and the plateau (``"steepest"``: stays on the edge of a thin wall under
        an elongated PSF and of a noisy or clipped one, where the half level does not, but is
        pulled towards a bright layer a few PSF widths inside the wall; :mod:`nemo.refine`).
    level_offsets : ndarray, optional
        Per sample of the blurred field (its shape: the image's sampled at ``step``), in the image's
        intensity units, subtracted from the field before meshing at a given ``threshold``: separate
        objects' own half levels minus the stack's, read on another image (the image before
        deconvolution, :func:`checked_half_level`; :func:`nemo.stages.mesh`).

    Returns
    -------
    trimesh.Trimesh
        Vertices (N, 3) in physical x, y, z; faces (F, 3) wound so that normals point out of
        the object. ``mesh.metadata["nemo_surface"]`` records the iso-level and parameters,
        ``border``, ``cap_faces`` (faces on the border planes), ``rim_vertices`` and
        ``rim_loops`` (the open rim; 0 for a closed surface), and the refinement: ``refine``
        (applied or not), ``refine_sigma``, ``refine_to`` (the edge used), ``refined``/``rejected``
        vertices and the shifts' ``shift_median``/``shift_abs_p95`` (:func:`nemo.refine.refine_vertices`).

    Raises
    ------
    NemoError
        Bad shapes or parameters; a constant (e.g. all-dark) image; a threshold or mask that
        selects no voxel or every voxel.
    """
    (dz, dy, dx), step, sigma = _check_reconstruct_args(spacing, sigma, keep, edge, step, smooth_iter, pass_band)
    refine_to = "level" if refine_to is None else refine_to
    if refine_to not in ("level", "steepest"):
        raise NemoError(f"refine_to must be 'level' or 'steepest', got {refine_to!r}")
    if border not in ("open", "closed"):
        raise NemoError(f"border must be 'open' or 'closed', got {border!r}")
    source, shape, scale, mask = _source(volume, mask)
    _check_stack_depth(shape, step)

    sig_vox = (sigma / dz, sigma / dy, sigma / dx)
    with log_step(f"blurring {shape[0]}x{shape[1]}x{shape[2]} voxels (sigma {sigma:g} {unit})"):
        field = _blur_sampled(source.view(np.uint8) if source.dtype == bool else source, sig_vox, step)
    # marching cubes now runs at step 1 on the sampled grid (spacing x step): identical to
    # scikit-image's step_size=step on the full blurred volume, at a fraction of the cost
    sampled_shape = field.shape
    padded = _pad_with_minimum(field)
    del field
    inner = padded[_PAD:-_PAD, _PAD:-_PAD, _PAD:-_PAD]
    if level_offsets is not None:
        if np.shape(level_offsets) != sampled_shape or isinstance(parse_threshold(threshold), str):
            raise NemoError(f"level_offsets must have the blurred field's shape {sampled_shape} and go with a given "
                            f"threshold; got shape {np.shape(level_offsets)} and threshold {threshold!r}")
        _subtract_by_slabs(inner, level_offsets, 1.0 / scale)
        logger.info("separate objects meshed at their own half levels, read on the image before deconvolution")
    vmin, vmax = float(inner.min()), float(inner.max())
    level, thr, how, background = _iso_level(inner, vmin, vmax, mask is not None, threshold, edge, scale,
                                             (dz * step, dy * step, dx * step))
    logger.info("iso-level %.4g (%s threshold %.4g)", level * scale, how, thr * scale)
    object_levels, region_peaks = [], []
    if isinstance(how, str):  # own levels only at the half edge and without refine (it crosses the one level)
        object_levels, region_peaks, _ = _object_levels(inner, thr, background, level, how, np.array([dz, dy, dx]) * step,
                                                     shift=edge in ("half", "profile") and not refine)
        if object_levels:
            logger.info("%d separate objects at their own half levels: %s (the stack's %.4g)", len(object_levels),
                        listed((f"{lev * scale:.4g}" for lev in object_levels), sep=", "), level * scale)
    del inner

    box = (np.array(sampled_shape[::-1]) - 1) * step * np.array([dx, dy, dz])
    mesh = _level_surface(padded, level, (dz, dy, dx), step, box, unit, keep)
    profile_info = _profile_skipped(edge, mask is not None, how, object_levels)
    if edge == "profile" and not profile_info and len(mesh.faces):
        mesh, level, profile_info = _at_profile_level(mesh, source, padded, level, (dz, dy, dx), step, box, keep)
        profile_info = {"level": level * scale, **profile_info, "level_half": profile_info["level_half"] * scale}
        if profile_info["level"] is not None:
            logger.info("iso-level from the walls' profiles %.4g (%d of %d rays fitted; the half level %.4g)",
                        profile_info["level"], profile_info["fitted"], profile_info["rays"], profile_info["level_half"])
    edge_check = {}
    if edge == "half" and isinstance(how, str) and mask is None and not object_levels and len(mesh.faces):
        level, edge_check = _checked_level(mesh, source, padded, level, (dz, dy, dx), step, scale)
        if edge_check["corrected"]:  # plain walls, a small offset: meshed again at (or towards) their profiles' level
            mesh = _level_surface(padded, level, (dz, dy, dx), step, box, unit, keep)
    snap_info = _snap(mesh, padded, level, (dz, dy, dx), step, box)
    del padded
    if smooth_iter > 0:
        with log_step(f"Taubin smoothing ({smooth_iter} iterations, {len(mesh.vertices)} vertices)"):
            smoothed = _taubin(np.asarray(mesh.vertices), np.asarray(mesh.faces), smooth_iter, pass_band)
            mesh.vertices = np.clip(smoothed, 0.0, box)
    ref_info = _refine(mesh, source if mask is None else None, level, (dz, dy, dx), step, refine,
                       refine_sigma, sigma, box, refine_to, background, edge != "threshold" or not isinstance(how, str))
    mesh, rim_info = _apply_border(mesh, border, box)
    mesh.metadata["nemo_surface"] = {
        "level": float(level) * scale, "threshold": float(thr) * scale, "method": str(how),
        "sigma": sigma, "step": step, "smooth_iter": int(smooth_iter), "keep": keep, "edge": edge,
        "spacing": [dz, dy, dx], "border": border, **snap_info, **rim_info, **ref_info,
        "object_levels": [lev * scale for lev in object_levels], "region_peaks": region_peaks,
        **({"profile": profile_info} if profile_info else {}),
        **({"edge_check": edge_check} if edge_check else {}),
    }
    mesh.metadata.pop("parent_faces", None)
    mesh.metadata.pop("parent_vertices", None)
    mesh.metadata["spacing"] = (dz, dy, dx)  # saved in the PLY header: peel checks the image
    return mesh


def _profile_rays(spacing: tuple[float, float, float], step: int) -> tuple[np.ndarray, float]:
    """The wall profiles' sample spacing (3,) along z, y, x (the marching cubes' step) and their reach
    (:data:`PROFILE_MAX_DEPTH_VOXELS` of the coarser axis, at least twice the finer one)."""
    sample = np.asarray(spacing, dtype=np.float64) * step
    return sample, PROFILE_MAX_DEPTH_VOXELS * max(float(max(spacing)), 2 * float(min(spacing)))


def _at_profile_level(mesh: trimesh.Trimesh, source: np.ndarray, padded: np.ndarray, level: float,
                      spacing: tuple[float, float, float], step: int, box: np.ndarray,
                      keep: str) -> tuple[trimesh.Trimesh, float, dict]:
    """``mesh`` remade at the level the walls' fitted profiles imply (:func:`nemo.refine.wall_profile_level`),
    the level and the record; ``mesh`` and ``level`` as they are when too few rays fit (a filled object
    larger than the rays' reach, a mesh of a few faces)."""
    from nemo.refine import wall_profile_level

    sample, reach = _profile_rays(spacing, step)
    pieces = np.zeros(len(mesh.vertices), dtype=np.int64)
    pieces[np.asarray(mesh.faces)] = face_components(np.asarray(mesh.faces), len(mesh.vertices))[:, None]
    with log_step(f"fitting wall profiles along {min(len(mesh.vertices), 4000)} normals"):
        found, info = wall_profile_level(source, spacing, np.asarray(mesh.vertices), _vertex_normals(mesh), padded,
                                         level, sample, -_PAD * sample, reach, labels=pieces)
    info = {**info, "level_half": float(level)}
    by_piece = list((info.pop("levels_by_label", None) or {}).values())
    if found is not None and len(by_piece) > 1 and max(by_piece) - min(by_piece) > 0.1 * info["contrast"]:
        logger.warning("the surface's pieces have walls of different brightness (their levels %s): one level, the "
                       "median %.4g, serves them all, so a dim object shrinks; edge: half gives separate objects their "
                       "own half levels", listed((f"{x:.4g}" for x in sorted(by_piece)), sep=", "), found)
        info["piece_levels"] = sorted(by_piece)
    if found is not None and (info.get("misfit") or 0.0) > PROFILE_MAX_MISFIT:
        logger.warning("the walls' profiles are not plain blurred boxes (misfit %.3g: bright films, a sheet or a "
                       "gradient inside the wall, or a clipped plateau): their fitted contrast follows the bright "
                       "part, and walls can move inward (a bright sheet inside a 10 µm wall moved one 2.8 µm); compare "
                       "with edge: half (level %.4g; the profiles' %.4g)", info["misfit"], level, found)
    if info["below_crest"] is not None and found is None:
        logger.warning("the walls' fitted profiles put the level above the blurred wall's crest on %.0f %% of the rays "
                       "(a wall thinner than the blur, e.g. a membrane under a z-elongated PSF, or a dim wall whose "
                       "bright texture raises the fitted contrast: a surface there would tear): the surface stays at "
                       "the half level", 100 * info["below_crest"])
        return mesh, level, {**info, "level": None}
    if found is None or not float(padded.min()) < found < float(padded.max()):
        logger.warning("too few walls' profiles fitted (%d of %d rays; a filled object more than %.3g across, or no "
                       "wall): the surface stays at the half level", info["fitted"], info["rays"], reach)
        return mesh, level, {**info, "level": None}
    again = _level_surface(padded, found, spacing, step, box, getattr(mesh, "units", None) or "um", keep)
    return again, float(found), info


def checked_half_level(volume: np.ndarray, spacing, sigma: float, step: int, threshold: str = "yen",
                       shift: bool = True) -> tuple[float, dict, dict]:
    """The half level :func:`reconstruct` would mesh ``volume`` at with ``edge="half"`` and an automatic
    ``threshold``, after its check against the walls' own profiles (:func:`_edge_check`) and the
    correction that check makes, with the check's record.

    For a deconvolved frame: ``volume`` is the image *before* deconvolution, whose half level the
    deconvolved image is meshed at (:func:`nemo.stages.mesh`). Its walls' profiles are read on this
    image along the normals of its own iso-surface, as for a frame meshed without deconvolution: noise
    lowers the histogram's plateau and so the half level on both (a 6 µm shell under a 2.5 µm z-PSF
    read 0.25-0.31 µm too thick at SNR 10 and 0.43-0.50 µm at SNR 5 without the correction, 0.07-0.15 and
    0.12 with it; docs/validation.md), and deconvolving does not thin a wall thinner than the blur
    (``thinner_than_blur``). Separate objects of different brightness get their own half levels
    (:func:`_object_levels`; ``shift`` False: not, as :func:`reconstruct` with ``refine``) and no check
    (as in :func:`reconstruct`): the level is the stack's and the record empty.

    Returns
    -------
    level : float
        In ``volume``'s intensity units.
    check : dict
        :func:`_edge_check`'s record with ``image``: ``"before deconvolution"``; empty without a check.
    objects : dict
        ``levels`` (the objects' own levels, intensity units; empty when one level serves), ``peaks``
        (each compact region's brightest point, x, y, z: :func:`regions_per_object`) and ``offsets``
        (:func:`reconstruct`'s ``level_offsets``, or None).
    """
    (dz, dy, dx), step, sigma = _check_reconstruct_args(spacing, sigma, "all", "half", step, 0, 0.1)
    source, _, scale, _ = _source(volume, None)
    padded = _pad_with_minimum(_blur_sampled(source, (sigma / dz, sigma / dy, sigma / dx), step))
    inner = padded[_PAD:-_PAD, _PAD:-_PAD, _PAD:-_PAD]
    sample = (dz * step, dy * step, dx * step)
    level, thr, how, background = _iso_level(inner, float(inner.min()), float(inner.max()), False, threshold, "half",
                                             scale, sample)
    levels, peaks, offsets = (_object_levels(inner, thr, background, level, how, np.array(sample), shift=shift)
                              if isinstance(how, str) else ([], [], None))
    objects = {"levels": [lev * scale for lev in levels], "peaks": peaks,
               "offsets": None if offsets is None else np.multiply(offsets, np.float32(scale), out=offsets)}
    if levels:
        logger.info("%d separate objects at their own half levels, read on the image before deconvolution: %s (the "
                    "stack's %.4g)", len(levels), listed((f"{lev * scale:.4g}" for lev in levels), sep=", "), level * scale)
    box = (np.array(inner.shape[::-1]) - 1) * step * np.array([dx, dy, dz])
    mesh = _level_surface(padded, level, (dz, dy, dx), step, box, "um", "all") if not levels else None
    if mesh is None or not len(mesh.faces):
        return float(level) * scale, {}, objects
    level, check = _checked_level(mesh, source, padded, level, (dz, dy, dx), step, scale)
    return float(level) * scale, {**check, "image": "before deconvolution"}, objects


def _checked_level(mesh: trimesh.Trimesh, source: np.ndarray, padded: np.ndarray, level: float,
                   spacing: tuple[float, float, float], step: int, scale: float) -> tuple[float, dict]:
    """``level`` (the blurred field's units) after :func:`_edge_check` along ``mesh``'s normals and the share of
    the way to the walls' profiles' level it corrects, with the check's record."""
    check = _edge_check(mesh, source, padded, level, spacing, step, scale)
    if check["corrected"]:
        level += check["correction"] * (check["level_profile"] / scale - level)
    return level, check


def _edge_check(mesh: trimesh.Trimesh, source: np.ndarray, padded: np.ndarray, level: float,
                spacing: tuple[float, float, float], step: int, scale: float) -> dict:
    """The half level checked against the walls' own profiles (:func:`nemo.refine.wall_profile_level`
    on :data:`EDGE_CHECK_RAYS` rays).

    Where the walls are plain boxes (``misfit`` ≤ :data:`EDGE_CHECK_MAX_MISFIT`), ``offset`` is the
    profiles' level minus the half level over the walls' fitted contrast. A small positive offset, between
    :data:`EDGE_CHECK_MIN_CORRECTION` and :data:`EDGE_CHECK_MAX_OFFSET`, of walls whose boxes the
    half level cuts at :data:`EDGE_CHECK_MIN_CORRECTED_SHARE` of their height or more, and no larger
    than the image's noise explains (``offset_snr``, the offset × the SNR of :func:`image_noise`, at
    most :data:`EDGE_CHECK_MAX_NOISE_OFFSET`: noise lowers the histogram's plateau; a bright sheet
    inside the wall shifts the profiles' level more) is ``corrected``: the caller meshes at
    ``level_profile``, or ``correction`` (0-1) of the way to it where a value lies within the soft
    width of its limit (:data:`EDGE_CHECK_SOFT_OFFSET`, :data:`EDGE_CHECK_SOFT_NOISE_OFFSET`,
    :data:`EDGE_CHECK_SOFT_SHARE`). Where the offset the correction leaves, ``offset`` ×
    (1 − ``correction``), exceeds :data:`EDGE_CHECK_MAX_OFFSET` a warning says the walls are placed
    outward (thin or z-blurred walls: their crests never reach the plateau the half level is taken
    from) or inward, and the summary's quality control flags the frame. Textured walls (fibres by the
    surfaces) and walls the fit refuses get ``offset`` None: their profiles say nothing reliable about
    the level. Plain walls refused because they are thinner than the blur (their blurred crest stays below
    the profiles' level on more than :data:`nemo.refine.PROFILE_MAX_BELOW_CREST` of the rays, and the
    level at least :data:`EDGE_CHECK_MIN_LEVEL_SHARE` of the boxes' height: the boxes are the meshed
    walls, not bright fibres on a dim wall; at least :data:`EDGE_CHECK_MIN_FITTED` of the rays fitted)
    get ``thinner_than_blur``, that share of the rays: they come out about as thick as the blur,
    warned and flagged too.
    """
    from nemo.refine import PROFILE_MAX_BELOW_CREST, wall_profile_level

    sample, reach = _profile_rays(spacing, step)
    # the rays' vertices' normals only: a whole paper-scale mesh's would cost as much as the fits
    at = np.random.default_rng(0).permutation(len(mesh.vertices))[:EDGE_CHECK_RAYS]
    with log_step(f"checking the level against the wall profiles along {len(at)} normals"):
        found, info = wall_profile_level(source, spacing, np.asarray(mesh.vertices)[at], _vertex_normals(mesh, at),
                                         padded, level, sample, -_PAD * sample, reach, n_rays=EDGE_CHECK_RAYS)
    record = {"rays": info["rays"], "fitted": info["fitted"], "misfit": info.get("misfit"), "offset": None,
              "limit": EDGE_CHECK_MAX_OFFSET, "level_profile": None if found is None else float(found) * scale,
              "thinner_than_blur": None, "level_share": info.get("level_share"), "corrected": False,
              "offset_snr": None, "level_half": float(level) * scale, "correction": 0.0}
    if record["misfit"] is None or record["misfit"] > EDGE_CHECK_MAX_MISFIT:
        return record
    if found is None:  # plain walls the fit refused: too few fits, or walls thinner than the blur
        if ((info["below_crest"] or 0.0) > PROFILE_MAX_BELOW_CREST and info["level_share"] >= EDGE_CHECK_MIN_LEVEL_SHARE
                and info["fitted"] >= EDGE_CHECK_MIN_FITTED * info["rays"]):  # not a noisy mesh whose rays miss
            record["thinner_than_blur"] = float(info["below_crest"])
            logger.warning("the walls are thinner than the image's blur on %.0f %% of their profiles (their blurred "
                           "crests stay below the profiles' own half level): they come out about as thick as the "
                           "blur, placed outward, thickness overestimated (a membrane or thin wall under a "
                           "z-elongated PSF, which deconvolving does not thin; or a bright film by the wall's "
                           "surface, whose blur the profiles read)", 100 * record["thinner_than_blur"])
        return record
    record["offset"] = offset = float((found - level) / info["contrast"])
    share = (_soft_limit(offset, EDGE_CHECK_MIN_CORRECTION, EDGE_CHECK_SOFT_OFFSET, above=True)
             * _soft_limit(offset, EDGE_CHECK_MAX_OFFSET, EDGE_CHECK_SOFT_OFFSET))
    share *= _soft_limit(info["level_share"], EDGE_CHECK_MIN_CORRECTED_SHARE, EDGE_CHECK_SOFT_SHARE, above=True)
    snr = image_noise(source, level)["snr"] if share > 0 else None  # what noise lowering the plateau explains
    if snr is not None:
        record["offset_snr"] = offset * snr
        share *= _soft_limit(offset * snr, EDGE_CHECK_MAX_NOISE_OFFSET, EDGE_CHECK_SOFT_NOISE_OFFSET)
        record["correction"], record["corrected"] = share, share > 0
    if record["corrected"]:
        logger.info("the walls' own profiles put their edges at level %.4g, %+.0f %% of their contrast from the half "
                    "level %.4g (noise lowers the histogram's plateau): meshed at %s", found * scale, 100 * offset,
                    level * scale, "the profiles' level" if share == 1 else f"{100 * share:.0f} % of the way to it")
    if abs(offset) * (1.0 - record["correction"]) > EDGE_CHECK_MAX_OFFSET:  # what the correction leaves
        logger.warning("the walls' own profiles put their edges at level %.4g, the half level is %.4g (%+.0f %% of "
                       "the walls' contrast): the walls come out %s (thin or z-blurred walls, whose crests never "
                       "reach the plateau the half level is taken from); mesh.edge: profile meshes at the profiles' "
                       "level, with psf: auto or none", found * scale, level * scale, 100 * offset,
                       "outward (thicker)" if offset > 0 else "inward (thinner)")
    return record


def _soft_limit(value: float, limit: float, width: float, above: bool = False) -> float:
    """1 well below ``limit`` (well above with ``above``), 0 well beyond it, linear over ``limit`` ± ``width`` / 2;
    0 for NaN. Within 1e-9 of 0 or 1 it is 0 or 1 (the ramp's ends in floating point: 0.02 read 1e-16)."""
    t = (value - limit) / width + 0.5
    share = float(np.clip(t if above else 1.0 - t, 0.0, 1.0)) if np.isfinite(t) else 0.0
    return 0.0 if share < 1e-9 else 1.0 if share > 1.0 - 1e-9 else share


#: Rays of the half level's check (:func:`_edge_check`; ``edge: profile`` fits 4 000): the median over 500
#: is steady to ~1 % of the contrast at SNR 3, and the fits take ~0.2 s (they tripled a small mesh's time at 1 000).
EDGE_CHECK_RAYS = 500
#: Largest misfit of walls whose profiles check the half level: plain walls read ≤ 0.034 to SNR 3, a bright
#: sheet inside a wall 0.044-0.065, the real stacks 0.05-0.11 (as ``edge: profile`` warns, PROFILE_MAX_MISFIT).
EDGE_CHECK_MAX_MISFIT = 0.04
#: Largest offset of the half level from the walls' profiles' level, over their contrast, that passes:
#: plain walls of 6-10 µm read ≤ 0.05 to SNR 5, a 4 µm wall under a 1.5 µm z-PSF 0.02-0.13 clean to SNR 3
#: (its thickness +3 to +29 %; docs/validation.md, "The half level checked against the walls' own profiles").
EDGE_CHECK_MAX_OFFSET = 0.1
#: Smallest offset of the half level from plain walls' profiles' level (over their contrast) that is corrected:
#: noise-free plain walls read 0.002-0.02, where the half level is right and the profiles' level 0.04 µm off.
EDGE_CHECK_MIN_CORRECTION = 0.03
#: Largest offset × the image's SNR that is corrected: noise lowers the histogram's plateau by about 0.15-0.31 /
#: SNR of the contrast on plain walls (8-bit and 16-bit, clipped or not; independent data), while a bright sheet
#: inside the wall (0.74-1.53) or a thin z-blurred wall (0.73-2.4) offsets the level by more than noise explains.
EDGE_CHECK_MAX_NOISE_OFFSET = 0.45
#: Widths of the correction's soft limits (:func:`_soft_limit`): the share of the way to the profiles' level
#: (``correction``) rises from 0 to 1 across the offset's lower limit 0.03 ± 0.01 and falls to 0 across its upper
#: limit 0.1 ± 0.01 and the offset × SNR's 0.45 ± 0.05, so a time-lapse whose walls sit near a limit is not meshed
#: at levels a whole correction apart: the validation shells at SNR 10 read offsets 0.029, 0.030, 0.031 on three
#: seeds (corrected only the last, by 0.35 µm). The warning and the QC judge the offset the correction leaves.
EDGE_CHECK_SOFT_OFFSET = 0.02
EDGE_CHECK_SOFT_NOISE_OFFSET = 0.1
#: ... and across the level's share of the boxes' height 0.35 ± 0.05 (:data:`EDGE_CHECK_MIN_CORRECTED_SHARE`: plain
#: walls 0.42-0.49, a bright sheet inside a wall 0.25; z-blurred shells at SNR 3 read 0.34-0.39).
EDGE_CHECK_SOFT_SHARE = 0.1
#: Smallest height of the half level over the fitted boxes' at which the half level is corrected: plain walls read
#: 0.42-0.49 to SNR 3; a bright sheet inside a wall 0.25 (its boxes fit the sheet), walls thinner than the blur 0.17-0.27.
EDGE_CHECK_MIN_CORRECTED_SHARE = 0.35
#: Smallest height of the half level over the fitted boxes' (``level_share``) at which boxes the level tears
#: tell walls thinner than the blur: those read 0.17-0.27 (a 1 µm membrane under σz 1.5 µm; 2-4 µm walls under
#: σz 2-3 µm), the synthetic vesicles' 10 µm walls 0.06-0.07 (their boxes fit the bright fibres, not the dim wall).
EDGE_CHECK_MIN_LEVEL_SHARE = 0.12
#: Least share of the rays with a fitted wall at which refused ones tell walls thinner than the blur: those fit
#: 99-100 % of their rays; an under-blurred noisy wall whose rays miss it fitted 45 % (a review's false flag).
EDGE_CHECK_MIN_FITTED = 0.6


def _level_surface(padded: np.ndarray, level: float, spacing: tuple[float, float, float], step: int,
                   box: np.ndarray, unit: str, keep: str) -> trimesh.Trimesh:
    """The iso-surface of ``padded`` at ``level`` (marching cubes), wound outward, its ``keep`` components."""
    vertices, faces, code = _marching_cubes(padded, level, spacing, step, box)
    mesh = make_mesh(vertices, faces, unit=unit, fields={_CODE: code}, orient_outward=False)
    if signed_volume(mesh.vertices, mesh.faces) < 0:  # padded => closed => the solid has volume > 0
        mesh.faces = mesh.faces[:, ::-1]
    logger.info("marching cubes: %d vertices, %d faces", len(mesh.vertices), len(mesh.faces))
    return keep_components(mesh, keep)


#: Largest misfit (:func:`nemo.refine.box_misfit`) of walls whose profile level ``edge: profile`` takes
#: without a warning: plain walls read ≤ 0.03 to SNR 3, walls with bright films or a gradient 0.04-0.3.
PROFILE_MAX_MISFIT = 0.04

#: How deep a ray of ``edge: profile`` looks for a wall's far edge: this many of the largest voxel
#: side, and at least twice as many of the smallest.
PROFILE_MAX_DEPTH_VOXELS = 40


def _profile_skipped(edge: str, masked: bool, how, object_levels: list) -> dict:
    """Why ``edge: profile`` keeps the first level (``{"level": None, "skipped": reason}``, warned), else {}."""
    if edge != "profile":
        return {}
    reason = ("a mask gives the surface" if masked else "the threshold is a given level" if not isinstance(how, str)
              else "objects of different brightness keep their own half levels" if object_levels else None)
    if reason is None:
        return {}
    logger.warning("edge: profile not applied: %s", reason)
    return {"level": None, "skipped": reason}


def _snap(mesh: trimesh.Trimesh, padded: np.ndarray, level: float, spacing: tuple[float, float, float],
          step: int, box: np.ndarray) -> dict:
    """Snap ``mesh``'s marching-cubes vertices in place onto the cubic iso-surface of the padded
    field (:func:`nemo.refine.snap_to_level`: undoes the terraces of linear interpolation
    between coarse samples); vertices on the image border stay. The record."""
    from nemo.refine import snap_to_level

    if len(mesh.faces) == 0:
        return {"snapped": 0, "snap_abs_p95": 0.0}
    sample = np.asarray(spacing, dtype=np.float64) * step
    code = np.asarray(mesh.vertex_attributes[_CODE])
    with log_step(f"snapping {len(mesh.vertices)} vertices onto the cubic-spline iso-surface"):
        new, info = snap_to_level(np.asarray(mesh.vertices), _vertex_normals(mesh), padded, level, sample,
                                  -_PAD * sample, fixed=code != 0)
    mesh.vertices = np.clip(new, 0.0, box)
    return info


def _refine(mesh: trimesh.Trimesh, source: np.ndarray | None, level: float, spacing: tuple[float, float, float],
            step: int, refine: bool, refine_sigma: float | None, sigma: float, box: np.ndarray,
            refine_to: str = "level", background: float | None = None, half_level: bool = True) -> dict:
    """Refine ``mesh``'s vertices in place (:func:`nemo.refine.refine_vertices`); the record.

    ``source`` None (a mask) or ``refine`` False: no refinement. The profile image is ``source``
    blurred by ``refine_sigma`` (default :data:`REFINE_SNR` from :func:`image_noise`, at most
    ``sigma``; none for a clean image). ``refine_to`` "steepest" needs a half level and the
    background (:func:`_steepest_background`); without them it falls back to the level
    crossing (warned, recorded).
    """
    from nemo.refine import refine_vertices

    if not isinstance(refine, (bool, np.bool_)):
        raise NemoError(f"refine must be true or false, got {refine!r}")
    if refine_sigma is not None and not (np.isfinite(float(refine_sigma)) and float(refine_sigma) >= 0):
        raise NemoError(f"refine_sigma must be a length >= 0 (µm), got {refine_sigma!r}")
    if refine and source is None:
        warnings.warn("refine is ignored with a mask: a binary mask has no sub-voxel edge to refine to (the "
                      "surface records refine: false)", NemoWarning, stacklevel=3)
    if not refine or source is None or len(mesh.faces) == 0:
        return {"refine": False}
    noise = image_noise(source, level)
    if refine_sigma is None:
        refine_sigma = _sigma_for_snr(noise["snr"], spacing, REFINE_SNR, 0.0, sigma)
    if refine_to == "steepest":
        background = _steepest_background(background, noise["background"], level, half_level)
        refine_to = "steepest" if background is not None else "level"
    refine_sigma = float(refine_sigma)
    image = source
    if refine_sigma > 0:
        with log_step(f"blurring for the refinement (sigma {refine_sigma:.3g})"):
            image = ndi.gaussian_filter(source, [refine_sigma / d for d in spacing], output=np.float32, truncate=3.0)
    code = np.asarray(mesh.vertex_attributes[_CODE])
    with log_step(f"refining {len(mesh.vertices)} vertices"):
        new, info = refine_vertices(np.asarray(mesh.vertices), np.asarray(mesh.faces), _vertex_normals(mesh), image,
                                    spacing, level, step=step, fixed=code != 0, to=refine_to, background=background)
    mesh.vertices = np.clip(new, 0.0, box)
    logger.info("refinement: %d vertices on an edge, %d without one; median shift %.3g, |shift| p95 %.3g",
                info["refined"], info["rejected"], info["shift_median"], info["shift_abs_p95"])
    return {"refine": True, "refine_sigma": refine_sigma, "refine_to": refine_to, **info}


def _steepest_background(background: float | None, raw_background: float | None, level: float,
                         half_level: bool) -> float | None:
    """The background the steepest-edge band is built on, or None (warned) to refine to the level.

    The band is centred on the level, so the level must be the half level: an automatic
    threshold with ``edge: half`` (background from :func:`_auto_level`) or a given intensity
    (background: the raw image's, :func:`image_noise`), not ``edge: threshold``.
    """
    background = raw_background if background is None else background
    if half_level and background is not None and background < level:
        return background
    why = "the surface is at the automatic threshold (edge: threshold), not the half level" if not half_level \
        else "no background level was measured below it"
    warnings.warn(f"refine_to steepest needs the half level between background and plateau, but {why}: refining "
                  "to the level crossing instead (the surface records refine_to: level)", NemoWarning, stacklevel=4)
    return None


def _vertex_normals(mesh: trimesh.Trimesh, at: np.ndarray | None = None) -> np.ndarray:
    """Unit area-weighted vertex normals (N, 3), or of the vertices ``at`` only (len(at), 3, from
    their own faces: cheaper on a large mesh); NaN where the faces around a vertex have no area."""
    vertices, faces = np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces)
    if at is not None:
        chosen = np.zeros(len(vertices), dtype=bool)
        chosen[at] = True
        faces = faces[chosen[faces].any(axis=1)]
    normals, areas = face_normals_areas(vertices, faces)
    acc = np.stack([np.bincount(faces.ravel(), weights=np.repeat(normals[:, k] * areas, 3), minlength=len(vertices))
                    for k in range(3)], axis=1)
    acc = acc if at is None else acc[at]
    norm = np.linalg.norm(acc, axis=1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(norm > 0, acc / norm, np.nan)


#: Samples of padding (the blurred volume's minimum) around the sampled grid: closed surfaces.
_PAD = 1
#: Temporary vertex field of :func:`reconstruct`: the border planes a vertex lies on (:func:`_border_code`).
_CODE = "_nemo_border"
#: Vertex field (private: not written to files) of an opened surface (``border="open"``): the label
#: of the closed surface, caps included, that each vertex came from (:func:`find_objects`).
CLOSED_SURFACE_FIELD = "_nemo_closed_surface"


def _apply_border(mesh: trimesh.Trimesh, border: str, box: np.ndarray) -> tuple[trimesh.Trimesh, dict]:
    """Open the surface where the object meets the image border (``border="open"``), or keep the cap.

    The cap faces (:func:`_cap_faces`) were marked right after marching cubes and went through
    the smoothing with the rest (so the surface next to the rim is smoothed as in the closed
    surface); the vertices on a border plane are put back on it (the smoothing rounds the
    cap's edge) and the cap faces are dropped. The winding is unchanged: normals stay outward.

    Returns
    -------
    mesh : trimesh.Trimesh
        Without the temporary border field.
    info : dict
        ``cap_faces`` (faces on the border planes: removed with ``"open"``), ``rim_vertices``
        and ``rim_loops`` of the returned surface (0 for a closed one).
    """
    code = np.asarray(mesh.vertex_attributes.pop(_CODE)).astype(np.uint8)
    cap = _cap_faces(np.asarray(mesh.faces), code) if len(mesh.faces) else np.zeros(0, bool)
    n_cap = int(cap.sum())
    if border == "open" and n_cap:
        if cap.all():
            raise NemoError("the surface lies entirely on the image border (only cap faces): nothing is left "
                            "of it with `border` open; use `border` closed or check the threshold")
        # the closed surface each vertex belongs to, caps included: the pieces of one object that the cut
        # separates (the two faces of a sheet cut on every side) stay one object (find_objects)
        closed = np.full(len(mesh.vertices), -1.0)
        closed[np.asarray(mesh.faces).ravel()] = np.repeat(face_components(mesh.faces, len(mesh.vertices)), 3)
        mesh.vertex_attributes[CLOSED_SURFACE_FIELD] = closed
        verts = np.array(mesh.vertices, dtype=np.float64)
        for k in range(3):  # the rim back onto its border plane
            verts[(code >> (2 * k)) & 1 == 1, k] = 0.0
            verts[(code >> (2 * k + 1)) & 1 == 1, k] = box[k]
        mesh.vertices = verts
        mesh = _with_metadata(submesh(mesh, ~cap), mesh)
        logger.info("border open: removed %d cap faces where the object meets the image border", n_cap)
    info = rim(mesh.faces, len(mesh.vertices))
    return mesh, {"cap_faces": n_cap, "rim_vertices": info["n_vertices"], "rim_loops": info["n_loops"]}


def _check_stack_depth(shape: tuple[int, int, int], step: int) -> None:
    """Refuse a stack with fewer than :data:`MIN_PLANES` samples (at ``step``) along an axis.

    Two planes mesh to a band one sample tall whose every vertex lies on its rim; the error then
    came from the curvature fit, naming a triangle soup.
    """
    thin = [(name, n) for name, n in zip("ZYX", shape) if n < MIN_PLANES]
    if thin:
        name, n = thin[0]
        raise NemoError(f"the stack (Z, Y, X) = {tuple(shape)} has {n} sample(s) along {name}: a surface needs "
                        f"at least {MIN_PLANES} planes along every axis; check the file's axes (`nemo info FILE`: "
                        "channels or time points read as Z?) or give a 3-D stack")
    if -(-min(shape) // step) < MIN_PLANES:
        raise NemoError(f"step {step} (voxels) leaves fewer than {MIN_PLANES} samples along an axis of the stack "
                        f"(Z, Y, X) = {tuple(shape)}: give a step of at most {max(1, (min(shape) - 1) // 2)}")


def _check_reconstruct_args(spacing, sigma, keep, edge, step, smooth_iter, pass_band):
    """Checked spacing ``(dz, dy, dx)``, step (int) and σ (default :func:`default_sigma`)."""
    dz, dy, dx = check_spacing(spacing)
    if keep not in ("largest", "all"):
        raise NemoError(f"keep must be 'largest' or 'all', got {keep!r}")
    if edge not in ("half", "threshold", "profile"):
        raise NemoError(f"edge must be 'half', 'threshold' or 'profile', got {edge!r}")
    if isinstance(step, bool) or not isinstance(step, (int, np.integer)) or step < 1:
        raise NemoError(f"marching-cubes step must be a whole number of voxels >= 1, got {step!r}")
    step = int(step)
    if isinstance(smooth_iter, bool) or not isinstance(smooth_iter, (int, np.integer)) or smooth_iter < 0:
        raise NemoError(f"smoothing iterations must be a whole number >= 0, got {smooth_iter!r}")
    if not 0 < pass_band < 2:
        raise NemoError(f"pass_band must lie in (0, 2), got {pass_band!r}")
    if sigma is None:
        sigma = default_sigma((dz, dy, dx), step)
    sigma = float(sigma)
    if not np.isfinite(sigma) or sigma < 0:
        raise NemoError(f"sigma must be a length >= 0 (µm), got {sigma!r}")
    return (dz, dy, dx), step, sigma


def _source(volume: np.ndarray | None, mask: np.ndarray | None):
    """What is blurred: the mask (bool) when given, else the image made float32-safe.

    Returns
    -------
    source : ndarray, shape (Z, Y, X)
    shape : tuple
    scale : float
        The factor the image was divided by (:func:`_float32_safe`; 1 for a mask).
    mask : ndarray of bool or None
    """
    if volume is not None:
        volume = np.asarray(volume)
        if volume.ndim != 3:
            raise NemoError(f"the image must be a 3-D (Z, Y, X) stack, got an array of shape {volume.shape}")
    if mask is not None:
        mask = np.asarray(mask)
        if mask.ndim != 3 or (volume is not None and mask.shape != volume.shape):
            want = volume.shape if volume is not None else "(Z, Y, X)"
            raise NemoError(
                f"the mask has shape {mask.shape} but the image stack has shape {want}; "
                "give a mask with the same Z, Y, X size as the image"
            )
        mask = mask != 0
        n_on = int(np.count_nonzero(mask))
        if n_on == 0:
            raise NemoError("the mask is empty (no nonzero voxel): nothing to reconstruct; check the mask file")
        if n_on == mask.size:
            raise NemoError("the mask selects every voxel: there is no object boundary; check the mask file")
        source, shape, scale = mask, mask.shape, 1.0
    elif volume is None:
        raise NemoError("give an image volume or a mask")
    else:
        source, scale = _float32_safe(volume)
        shape = volume.shape
    if min(shape) < 2:
        raise NemoError(f"the stack {shape} is too thin for a surface: every axis needs at least 2 voxels")
    return source, shape, scale, mask


def _pad_with_minimum(field: np.ndarray) -> np.ndarray:
    """``field`` padded by :data:`_PAD` samples of its minimum (float32): objects touching the
    border give closed surfaces."""
    pad = _PAD
    padded = np.empty(tuple(s + 2 * pad for s in field.shape), dtype=np.float32)
    inner = padded[pad:-pad, pad:-pad, pad:-pad]
    inner[...] = field
    pad_value = float(inner.min())
    padded[:pad] = pad_value
    padded[-pad:] = pad_value
    padded[:, :pad] = pad_value
    padded[:, -pad:] = pad_value
    padded[:, :, :pad] = pad_value
    padded[:, :, -pad:] = pad_value
    return padded


def _iso_level(inner: np.ndarray, vmin: float, vmax: float, from_mask: bool, threshold, edge: str,
               scale: float, spacing=(1.0, 1.0, 1.0), quiet: bool = False) -> tuple[float, float, str | float, float | None]:
    """Iso-level of the blurred (scaled) field, the threshold it came from, how it was found and
    the background (:func:`_auto_level`; None for a mask or a given level).

    A mask is cut at 0.5 (mid-range when the blur is wider than the object); an automatic
    threshold goes through :func:`_auto_level`; a number is used as given (divided by
    ``scale``). Refused when the level selects no voxel or every voxel.
    """
    if from_mask:
        level, thr, how = 0.5, 0.5, "mask"
        if not vmin < level < vmax:  # blur wider than the object
            level = 0.5 * (vmin + vmax)
        return level, thr, how, None
    how = parse_threshold(threshold)
    if vmin == vmax:
        raise NemoError(
            f"the image is constant (every voxel = {vmin * scale:g}, e.g. an all-dark stack): no object to "
            "threshold; check the time point/channel and the file, or give a `mask`"
        )
    background = None
    if isinstance(how, str):
        thr, level, background = _auto_level(inner, how, edge, spacing, quiet)
    else:
        thr = level = how / scale  # the volume was divided by scale (_float32_safe)
    rng = f"blurred intensities {vmin * scale:.4g} to {vmax * scale:.4g}"
    if level >= vmax:
        raise NemoError(
            f"threshold {threshold!r} (level {level * scale:.4g}) selects no voxel ({rng}): the object is "
            "empty; lower `threshold`, use 'yen'/'otsu', or check the time point/channel"
        )
    if level <= vmin:
        raise NemoError(
            f"threshold {threshold!r} (level {level * scale:.4g}) selects every voxel ({rng}): there is no "
            "boundary; raise `threshold` or use 'yen'/'otsu'"
        )
    return level, thr, how, background


def _marching_cubes(padded: np.ndarray, level: float, spacing: tuple[float, float, float], step: int,
                    box: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Marching cubes of the padded field: clean vertices (N, 3) in x, y, z, outward faces (F, 3)
    and the border-plane code of every vertex (:func:`_border_code`).

    Coincident vertices are merged, cancelling faces and non-manifold vertices repaired, unused
    vertices dropped; the padding is removed from the coordinates and caps on the border are put
    on the image's extent ``box``.
    """
    from skimage import measure

    dz, dy, dx = spacing
    pad = _PAD
    with log_step(f"marching cubes (step {step} voxels)"):
        verts_zyx, faces, _, _ = measure.marching_cubes(padded, level, spacing=(dz * step, dy * step, dx * step),
                                                        allow_degenerate=False)
    # Where the level equals a voxel value, marching cubes puts several vertices on the same
    # point (zero-area faces, zero normals): merge them and drop the faces that collapse and
    # the vertices no face uses any more.
    verts_zyx, faces, _ = merge_coincident_vertices(np.asarray(verts_zyx, dtype=np.float64), faces)
    faces = _cancel_duplicate_faces(faces)
    verts_zyx, faces = split_nonmanifold_vertices(verts_zyx, faces)  # sheets touching at a vertex/edge
    used = np.zeros(len(verts_zyx), dtype=bool)
    used[faces.ravel()] = True
    if not used.all():
        faces = (np.cumsum(used) - 1)[faces]
        verts_zyx = verts_zyx[used]
    vertices = verts_zyx[:, ::-1] - pad * step * np.array([dx, dy, dz])
    code = _border_code(vertices, box, np.array([dx, dy, dz]) * step)
    # caps of objects cut by the border lie between the last sample and the pad: put them on
    # the border plane (the image's extent), also after smoothing
    np.clip(vertices, 0.0, box, out=vertices)
    # swapping z and x is a reflection, which reverses the winding; re-reverse it so normals
    # point down the intensity gradient (out of the object).
    faces = np.ascontiguousarray(faces[:, ::-1], dtype=np.int64)
    return vertices, faces, code


#: Tolerance (in samples) of a marching-cubes vertex on a border plane of the sampled grid.
_BORDER_TOL = 1e-4


def _border_code(vertices: np.ndarray, box: np.ndarray, sample: np.ndarray) -> np.ndarray:
    """Which border planes of the sampled grid each vertex lies on or beyond (in the padding).

    Parameters
    ----------
    vertices : ndarray, shape (N, 3)
        Physical x, y, z before clipping to the image's extent (the padding lies outside
        ``[0, box]``).
    box : ndarray, shape (3,)
        Position of the last sample along x, y, z.
    sample : ndarray, shape (3,)
        Sampling distance along x, y, z (spacing × step).

    Returns
    -------
    ndarray of uint8, shape (N,)
        Bit ``2 k`` set when the vertex lies at or below the plane ``axis k = 0``, bit ``2 k + 1``
        at or beyond ``axis k = box[k]`` (x, y, z = k 0, 1, 2); 0 for a vertex inside the grid.
    """
    tol = _BORDER_TOL * sample
    code = np.zeros(len(vertices), dtype=np.uint8)
    for k in range(3):  # six planes
        code |= (vertices[:, k] <= tol[k]).astype(np.uint8) << (2 * k)
        code |= (vertices[:, k] >= box[k] - tol[k]).astype(np.uint8) << (2 * k + 1)
    return code


def _cap_faces(faces: np.ndarray, code: np.ndarray) -> np.ndarray:
    """Faces of the artificial cap: all three vertices on or beyond the same border plane.

    Marching cubes closes an object cut by the image border inside the padding: every triangle
    of the cells between the last sample and the pad has its vertices on the border plane (the
    object's cross-section) or in the padding, and no triangle of the object's own surface has
    all three there (it would lie flat in the border plane).

    Returns
    -------
    ndarray of bool, shape (F,)
    """
    c = code[faces]
    return (c[:, 0] & c[:, 1] & c[:, 2]) != 0


# --------------------------------------------------------------------------- split
def split_mesh(
    mesh: trimesh.Trimesh,
    by: Literal["centre", "axis"] = "centre",
    axis: np.ndarray | None = None,
    centre: np.ndarray | None = None,
    keep: Literal["largest", "all"] = "all",
    component_majority: float = 0.9,
) -> tuple[trimesh.Trimesh, trimesh.Trimesh]:
    """Split a mesh into its inner and outer walls by the sign of ``n · (x − centre)`` or ``n · axis``.

    Each face goes to at most one half by the sign for its unit normal ``n`` and its centroid
    ``x``: ``> 0`` outer, ``< 0`` inner; zero-area faces (no normal, sign 0) go to neither.
    A connected component that lies almost entirely on one side (at least ``component_majority``
    of its area) goes to that side whole: on a noisy wall, bumps whose faces tilt past the
    radial direction would otherwise punch holes into it. Components that are really split
    (e.g. one open epithelium whose apical and basal sides meet at a rim) keep the per-face rule.
    A hollow shell cut by the image border (``border="open"``) has lost the cap joining its
    walls: they are separate open components and each goes whole to its side. By the centre, a
    hollow object's closed pieces go whole by their winding (:func:`_cavity_sides`: a closed piece
    wound inward is a cavity's wall): the walls of a hollow torus or bent tube turn both ways
    seen from any one centre.

    Parameters
    ----------
    mesh : trimesh.Trimesh
        Typically a reconstructed solid shell (both walls, normals out of the solid).
    by : {"centre", "axis"}
    axis : array_like, shape (3,), optional
        Reference direction (x, y, z) for ``by="axis"``.
    centre : array_like, shape (3,), optional
        Reference point for ``by="centre"``; default the area-weighted centroid of the surface.
    keep : {"largest", "all"}
        Keep only the largest connected component of each half (drops loose fragments).
    component_majority : float
        Area fraction in (0.5, 1] above which a whole connected component follows its majority
        side; 1 gives the pure per-face rule (also for a hollow object's closed pieces).

    Returns
    -------
    inner, outer : trimesh.Trimesh
        Re-indexed meshes with the parent's units and vertex fields. **Both have normals
        pointing away from the centre (along +axis)**: the inner half is flipped, so the
        inner wall of a hollow shell comes out as a sphere with outward normals.
        ``metadata["parent_faces"]`` maps their faces to ``mesh``'s faces.

    Raises
    ------
    NemoError
        Unknown ``by``, missing or zero axis, or a half with no face (the mesh has one wall).
    """
    side, labels, area, outer_frac, ref = _face_sides(mesh, by, axis, centre)
    if not 0.5 < component_majority <= 1.0:
        raise NemoError(f"component_majority must be in (0.5, 1], got {component_majority}")
    if by == "centre" and component_majority < 1.0:  # 1: the pure per-face rule
        outer_frac = _cavity_sides(mesh, labels, outer_frac, area)
    has_normal = side != 0
    side = np.where(has_normal & (outer_frac >= component_majority)[labels], 1.0, side)
    side = np.where(has_normal & (1.0 - outer_frac >= component_majority)[labels], -1.0, side)
    outer_sel = side > 0
    inner_sel = side < 0
    n_out, n_in = int(outer_sel.sum()), int(inner_sel.sum())
    if n_out == 0 or n_in == 0:
        side = "inner" if n_in == 0 else "outer"
        raise NemoError(
            f"splitting by {ref} leaves the {side} half empty: the mesh has a single wall "
            "(e.g. a filled object or a droplet) or the reference is outside it; for one wall set "
            "`split` auto or none (config mesh.split), else another split reference (`axis`)"
        )
    inner = keep_components(submesh(mesh, inner_sel, flip=True), keep)
    outer = keep_components(submesh(mesh, outer_sel), keep)
    logger.info("split by %s: inner %d faces, outer %d faces", ref, len(inner.faces), len(outer.faces))
    return inner, outer


#: ``split: auto`` takes a single surface that turns towards its centre over part of its area
#: (:func:`count_walls`' ``mixed_fraction``) for two walls joined at a rim or a tear when it is a thin
#: sheet: its :func:`sheet_width` at most this fraction of its size √(A/4π). Measured at 1 µm voxels,
#: SNR 10: shells of a 6 µm wall (R 32) torn at one or both poles, or thinner than the blur at one,
#: 0.12-0.15; a cup of a 4 µm wall 0.13; tori of tube radius 5 and 10 (ring 30) 0.45 / 0.65, a cup of
#: a 12 µm wall 0.40, a banana-shaped cell 0.91 (a torn shell's wall of 30 % of its radius: ~0.23).
SHEET_MAX_WIDTH = 0.25
#: Rays cast by :func:`sheet_width` (from this many random vertices).
SHEET_RAYS = 1000
#: ... and it wraps a cavity round its centre: :func:`cavity_enclosure` at least this (a torn shell
#: 0.9+, a cup about half; a filled cell whose centre lies in its solid 0, a bent filament or a torus
#: well below).
CAVITY_MIN_ENCLOSURE = 0.4
#: ... and it is a sheet, not a tube: the normals within half its width of a vertex keep, on average,
#: a cosine of at least this with its own (:func:`sheet_flatness`; a wall's two faces are near-parallel
#: planes at that scale, while a filament's normals turn round its axis within its radius: a coiled
#: filament was split as a torn shell, an independent review). Measured at 1 µm and 0.5 × 0.5 × 1.5 µm
#: voxels: torn shells and cups 0.97-0.99, a hollow bent tube's wall (radii 5-9 µm) 0.975 / 0.947; a
#: loose filled coil 0.92 / 0.83, filaments caging a sphere 0.94 (a narrow margin: docs/validation.md);
#: a torus's tube at its diameter 0.87 on a coarse or a dense mesh.
SHEET_MIN_FLATNESS = 0.94


def sheet_width(mesh: trimesh.Trimesh, n_rays: int = SHEET_RAYS, rng: int = 0) -> float:
    """Median distance across the solid a surface encloses, along its inward normals.

    From ``n_rays`` random vertices a ray is cast along −N to where it leaves the solid: the wall's
    thickness of a shell torn open (its inner and outer walls one surface), the tube's diameter of
    a filled torus, the diameter of a ball.

    Parameters
    ----------
    mesh : trimesh.Trimesh
        Surface with outward normals (closed, or open where the image border cuts it).
    n_rays : int
        Rays cast (fewer on a smaller mesh).
    rng : int
        Seed of the vertices chosen.

    Returns
    -------
    float
        The median distance in the mesh unit; NaN when fewer than half the rays find the far side
        (an open surface whose solid the border cuts away).
    """
    from nemo.mesh import mean_edge_length
    from nemo.morphology import _ray_distance

    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    at = np.random.default_rng(rng).permutation(len(vertices))[:n_rays]
    normals = _vertex_normals(mesh, at)
    ok = np.isfinite(normals).all(axis=1)
    across = _ray_distance(mesh, vertices[at][ok], -normals[ok], 1e-3 * mean_edge_length(mesh), back_off=False)
    return float(np.nanmedian(across)) if np.isfinite(across).sum() >= 0.5 * len(at) else float("nan")


def sheet_flatness(mesh: trimesh.Trimesh, width: float, n_vertices: int = SHEET_RAYS, rng: int = 0) -> float:
    """How flat a surface is at half its width: the median, over ``n_vertices`` random vertices, of the
    mean cosine between a vertex's normal and those of the vertices within ``width`` / 2 of it.

    About 1 for a sheet whose width (:func:`sheet_width`) is small beside its radius of curvature (a
    torn shell's wall); about 0.85 for a tube, whose normals turn round its axis within its radius.

    Returns
    -------
    float
        In [−1, 1]; NaN for a width that is not positive and finite.
    """
    from scipy.spatial import cKDTree

    if not (np.isfinite(width) and width > 0):
        return float("nan")
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    generator = np.random.default_rng(rng)
    at = generator.permutation(len(vertices))[:n_vertices]
    # neighbours drawn from a subset with ~40 vertices in a ball of radius width / 2, so that the 64
    # nearest span that ball also on a dense mesh (all the vertices: a coarse one)
    n_sample = int(min(len(vertices), max(64.0, 40.0 * float(mesh.area) / (np.pi * (0.5 * width) ** 2))))
    sample = generator.permutation(len(vertices))[:n_sample]
    distance, near = cKDTree(vertices[sample]).query(vertices[at], k=64, distance_upper_bound=0.5 * width)
    found = np.isfinite(distance)
    # the normals of the drawn vertices only (a dense mesh's all would cost more than the query)
    cosines = np.einsum("ikj,ij->ik", _vertex_normals(mesh, sample)[np.where(found, near, 0)], _vertex_normals(mesh, at))
    with np.errstate(invalid="ignore"):
        mean = np.nansum(np.where(found, cosines, 0.0), axis=1) / found.sum(axis=1)
    return float(np.nanmedian(mean))


def cavity_enclosure(mesh: trimesh.Trimesh, centre: np.ndarray | None = None, n_rays: int = 256) -> float:
    """Share of the directions from ``centre`` in which the first face met is entered (its outward
    normal faces the ray): how far the surface wraps an empty cavity round the centre.

    A shell torn at a pole wraps its cavity in nearly every direction, a cup in about half; from a
    centre inside the solid (a filled cell, a fried-egg-shaped adherent cell) every first face is
    left, not entered: 0; a bent filament or a torus round its hole meets few directions.

    Parameters
    ----------
    mesh : trimesh.Trimesh
        Surface with outward normals.
    centre : array_like, shape (3,), optional
        Default: the area-weighted centroid of the faces (as :func:`count_walls`).
    n_rays : int
        Directions, spread evenly over the sphere (a Fibonacci lattice).

    Returns
    -------
    float
        In [0, 1].
    """
    from nemo.geometry import surface_centre

    vertices, faces = np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces)
    centre = surface_centre(mesh) if centre is None else centre
    k = np.arange(n_rays) + 0.5
    polar, azimuth = np.arccos(1 - 2 * k / n_rays), np.pi * (1 + 5**0.5) * k
    directions = np.column_stack([np.sin(polar) * np.cos(azimuth), np.sin(polar) * np.sin(azimuth), np.cos(polar)])
    hit = np.asarray(mesh.ray.intersects_first(np.tile(np.asarray(centre, dtype=np.float64), (n_rays, 1)),
                                               directions), dtype=np.int64)
    corners = vertices[faces[hit[hit >= 0]]]
    normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    return float(np.sum(np.einsum("ij,ij->i", normals, directions[hit >= 0]) < 0) / n_rays)


def count_walls(mesh: trimesh.Trimesh, centre: np.ndarray | None = None,
                min_fraction: float = OBJECT_MIN_AREA) -> tuple[int, float, float]:
    """Walls of one object for ``mesh.split: auto``: 2 when a separate surface faces its centre.

    Each connected piece of the surface is sorted by the sign of n · (x − centre) over its area,
    as :func:`split_mesh` sorts the pieces that lie at least 90 % on one side. The object has two
    walls when its largest piece turned towards the centre (a hollow shell's inner wall, closed
    or cut open by the image border) has at least ``min_fraction`` of the area of its largest
    piece turned away (the bar of an object, :func:`find_objects`); otherwise one. A closed piece
    wound inward (a cavity's wall) is turned towards the centre wherever the centre lies, and then
    every closed piece wound outward away from it (:func:`_cavity_sides`): a hollow torus has two
    walls. A droplet, a filled cell or a ball with a small cavity have one; so has a single
    surface that turns towards its centre over part of its area (a filled torus, a banana-shaped
    cell, a sheet cut by the image border, a cup whose two sides meet at its lip): ``split:
    centre`` sorts those face by face. ``mixed_fraction`` says how much of the surface such
    pieces hold (by the centre's rule alone); :func:`sheet_width` and :func:`cavity_enclosure` then
    tell a thin sheet round a cavity (two walls joined at a rim or a tear) from a solid (``split:
    auto``, :func:`nemo.stages.mesh`).

    Parameters
    ----------
    mesh : trimesh.Trimesh
        One object's surface with the surfaces nested in it (:func:`one_object`).
    centre : array_like, shape (3,), optional
        Reference point (default: the area-weighted centroid).
    min_fraction : float
        Smallest inner area relative to the outer.

    Returns
    -------
    walls : int
        1 or 2.
    inner_fraction : float
        Area of the largest piece turned towards the centre over that of the largest turned
        away (0 when there is none).
    mixed_fraction : float
        Area of the pieces turned neither way over 90 % of their area, over the whole area.
    """
    if len(mesh.faces) == 0:
        return 1, 0.0, 0.0
    _, labels, total, outward, _ = _face_sides(mesh, "centre", None, centre)
    sides = _cavity_sides(mesh, labels, outward, total)
    outer, inner = total[sides >= 0.9], total[sides <= 0.1]
    mixed = float(total[(outward > 0.1) & (outward < 0.9)].sum() / max(total.sum(), 1e-300))
    fraction = float(inner.max() / outer.max()) if len(inner) and len(outer) else 0.0
    return (2 if fraction >= min_fraction else 1), fraction, mixed


def _cavity_sides(mesh: trimesh.Trimesh, labels: np.ndarray, outward: np.ndarray, area: np.ndarray,
                  min_fraction: float = OBJECT_MIN_AREA) -> np.ndarray:
    """``outward`` (the outward area fraction per connected piece, :func:`_face_sides`) with the
    walls of each cavity set by their winding: a closed piece wound inward (negative enclosed
    volume: its normals point out of the solid into the cavity) of at least ``min_fraction`` of the
    area of a closed piece wound outward that encloses it is inner (0), and that piece outer (1),
    whatever the centre sees. The centre alone reads a torus's or a bent tube's walls as turning
    both ways (an independent review: a hollow torus counted one wall, its inner wall dropped). Other
    pieces keep ``outward``: a small void in a wall, or a separate piece wound inward (an imported
    mesh's), changes nothing, and a cup whose two faces meet at its lip is still sorted face by face.
    ``labels`` (per face), ``outward`` and ``area`` (per piece) are :func:`_face_sides`'s."""
    from nemo.geometry import boundary_edges

    faces = np.asarray(mesh.faces)
    v = np.asarray(mesh.vertices, dtype=np.float64)
    v = v - v.mean(axis=0)  # the enclosed volume of a closed piece does not depend on the origin
    n = len(outward)
    volume = np.bincount(labels, weights=np.einsum("ij,ij->i", v[faces[:, 0]], np.cross(v[faces[:, 1]],
                                                                                          v[faces[:, 2]])), minlength=n)
    on_rim = np.zeros(len(v), dtype=bool)
    on_rim[boundary_edges(faces).ravel()] = True
    is_open = np.zeros(n, dtype=bool)
    is_open[labels[on_rim[faces].any(axis=1)]] = True
    shells = np.flatnonzero(~is_open & (volume > 0))
    sides = np.asarray(outward, dtype=np.float64).copy()
    for cavity in np.flatnonzero(~is_open & (volume < 0)):  # a loop over cavities: a hollow object has few
        big = shells[area[shells] * min_fraction <= area[cavity]]
        if not len(big):
            continue
        probe = v[faces[labels == cavity][0, 0]][None]
        around = [s for s in big if abs(_winding_numbers(probe, v, faces[labels == s])[0]) > 0.5]
        if around:
            sides[cavity] = 0.0
            sides[around] = 1.0
    return sides


def _face_sides(mesh: trimesh.Trimesh, by: str, axis, centre) -> tuple[np.ndarray, np.ndarray, np.ndarray,
                                                                        np.ndarray, str]:
    """Sides of :func:`split_mesh`: (sign of n · (x − centre) or n · axis per face (0: no normal),
    connected-piece label per face, area per piece, outward area fraction per piece, the
    reference named)."""
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    faces = np.asarray(mesh.faces)
    if len(faces) == 0:
        raise NemoError("cannot split an empty mesh")
    normals, areas = face_normals_areas(vertices, faces)
    centroids = vertices[faces].mean(axis=1)
    if by == "centre":
        if centre is None:
            centre = (centroids * areas[:, None]).sum(axis=0) / areas.sum()
        centre = np.asarray(centre, dtype=np.float64).reshape(3)
        sign = np.einsum("ij,ij->i", normals, centroids - centre)
        ref = f"centre ({centre[0]:.4g}, {centre[1]:.4g}, {centre[2]:.4g})"
    elif by == "axis":
        if axis is None:
            raise NemoError("split by axis needs an axis: give `axis` (x, y, z)")
        axis = np.asarray(axis, dtype=np.float64).reshape(3)
        norm = np.linalg.norm(axis)
        if not np.isfinite(norm) or norm == 0:
            raise NemoError(f"the split axis must be a non-zero vector, got {axis.tolist()}")
        sign = normals @ (axis / norm)
        ref = f"axis ({axis[0]:.4g}, {axis[1]:.4g}, {axis[2]:.4g})"
    else:
        raise NemoError(f"split by must be 'centre' or 'axis', got {by!r}")
    side = np.sign(sign)  # zero-area faces have no normal (sign 0): they stay out of both halves
    labels = trimesh.graph.connected_component_labels(mesh.face_adjacency, len(faces))
    total = np.bincount(labels, weights=areas)
    return side, labels, total, np.bincount(labels, weights=areas * (side > 0)) / np.maximum(total, 1e-300), ref


# --------------------------------------------------------------------------- sphere fit
def fit_sphere(mesh: trimesh.Trimesh | np.ndarray) -> tuple[np.ndarray, float]:
    """Least-squares (algebraic) sphere through a mesh's vertices.

    Solves ``|x|² = 2 c·x + (r² − |c|²)`` for ``c`` and ``r`` in the least-squares sense
    (coordinates centred first for conditioning).

    Parameters
    ----------
    mesh : trimesh.Trimesh or ndarray, shape (N, 3)

    Returns
    -------
    centre : ndarray, shape (3,)
    radius : float
    """
    points = np.asarray(mesh.vertices if isinstance(mesh, trimesh.Trimesh) else mesh, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3 or len(points) < 4:
        raise NemoError(f"a sphere fit needs at least 4 points (N, 3), got shape {points.shape}")
    mean = points.mean(axis=0)
    p = points - mean
    a = np.column_stack([2.0 * p, np.ones(len(p))])
    b = np.einsum("ij,ij->i", p, p)
    sol, *_ = np.linalg.lstsq(a, b, rcond=None)
    c = sol[:3]
    r2 = sol[3] + c @ c
    if not r2 > 0:
        raise NemoError("the points do not lie on a sphere (degenerate fit)")
    return c + mean, float(np.sqrt(r2))

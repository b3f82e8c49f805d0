"""One function per step of the paper's analysis, with the defaults that follow the data.

``nemo run``, the step commands (``nemo mesh``, ``nemo peel``, ...) and the workflow's rules all
call these functions, so the same parameters give the same numbers whichever way a frame is
analysed. Each takes its section of the config (:mod:`nemo.config`; None values = defaults),
fills every data-derived default with a number and returns it next to the result, so the
resolved values can be stored in the table's provenance and printed.

Data-derived defaults (``edge`` = mean edge length of the analysed mesh, ``R_obj`` = the
radius of a sphere of the same area, ``sqrt(area / 4π)``):

==========================  =====================================================================
``mesh.step``               1 voxel; 2 for stacks above :data:`STEP2_VOXELS` voxels (memory)
``mesh.sigma``              noise-aware (nemo.surface.auto_sigma): at least half the sampling
                            distance ``step (dx + dy) / 4``, enough for a blurred SNR of 20
``curvature.radius``        where pilot fits' curvature changes least with the radius, 4 to 32
                            ``edge``, at most ``0.6 R_obj`` of the largest piece (closed) or the
                            median rim distance (open); nemo.morphology.default_radius
``curvature.smooth``        H, K averaged over ``0.35 radius`` (σ, debiased) along the surface
``directors.patch_radius``  ``0.1 R_obj`` (the paper: 20 µm on R = 200 µm), at least ``8 edge``
``directors.n_patches``     30 per patch area, at most the number of vertices
``directors.pixel``         ``edge / 4``, at least ``patch_radius / 97`` (micro-images ≤ 195 px)
                            (these three: nemo.directors, the same defaults as ``directors()``)
``directors.sigma``         4 px, widened to at most two edges where the directors scatter (noise-aware)
``directors_import``        ``max_distance``: ``2 edge``; the order radius of imported directors
                            holds about 10 of them (1.78 × their spacing ``sqrt(area / n)``)
``order.radius``            ``2.5 patch_radius`` (the paper: 50 µm for 20 µm patches)
``defects.min_distance``    the averaging radius; ``contour_radius``: 1.5 × it (nemo.defects)
==========================  =====================================================================
"""

from __future__ import annotations

import math
import os
import warnings

import numpy as np
import pandas as pd
import trimesh

from nemo import config as nconfig
from nemo import objects
from nemo._log import OBJECTS_LOGGED, listed, logger, quiet_objects
from nemo.errors import NemoError, NemoWarning, ObjectTooSmallError
from nemo.mesh import object_radius  # the object's scale, used by the defaults below
from nemo.psf import check_psf, deconvolve, is_auto, meshes_deconvolved
from nemo.summary import QC_MIN_SNR
from nemo.tables import SCHEMAS

__all__ = ["object_radius", "mesh", "measure", "curvature", "curvature_defaults", "thickness", "peel", "directors",
           "directors_defaults", "import_directors", "order", "defects", "tracking_distance"]

#: Imported directors per default averaging disc (``order.radius`` of an imported layer).
IMPORTED_PER_DISC = 10.0

#: Stacks with more voxels than this are meshed every 2 voxels by default.
STEP2_VOXELS = 64_000_000
#: Default averaging radius in patch radii.
ORDER_PER_PATCH = 2.5


# ----------------------------------------------------------------------------- mesh
def mesh(
    volume: np.ndarray | None,
    spacing: tuple[float, float, float],
    params: dict | None = None,
    mask: np.ndarray | None = None,
    unit: str = "um",
    centre: np.ndarray | None = None,
    psf: tuple[float, float, float] | str | None = None,
    deconvolved: tuple[np.ndarray, dict] | None = None,
    mask_regions: np.ndarray | None = None,
) -> tuple[dict[str, trimesh.Trimesh], dict]:
    """Surface reconstruction (method note §2), split into inner/outer walls if configured.

    An object cut by the image border gives an open surface (``border: open``, the default;
    :func:`nemo.surface.reconstruct`), ``closed`` keeps the flat cap along the border.

    Objects (:func:`nemo.surface.find_objects`) are separate surfaces not nested in each other,
    each at least 10 % of the largest one's area (smaller specks are noise). With several,
    ``keep: largest`` analyses the largest (with the walls nested in it) and warns about the
    others; ``keep: all`` keeps every object, labels each vertex with its object (largest = 0;
    :mod:`nemo.objects`) and splits each about its own centre, so later steps analyse them
    one by one. ``split: auto`` (the default) splits an object only when it has two walls
    (:func:`nemo.surface.count_walls`); an object of one wall (a droplet) gets ``inner`` and
    ``outer`` equal to its whole surface, and no thickness (:func:`thickness`).

    Parameters
    ----------
    volume : ndarray, shape (Z, Y, X)
        The segmented channel (None when ``mask`` is given).
    spacing : (dz, dy, dx)
        Voxel size.
    params : dict, optional
        The ``mesh`` section.
    mask : ndarray of bool, shape (Z, Y, X), optional
        Object mask used instead of the threshold.
    psf : (σz, σy, σx), "auto" or "none", optional
        The PSF's standard deviations: the image is meshed deconvolved by it
        (:func:`nemo.psf.deconvolve`; noise, SNR and saturation are still those of the image);
        ``"auto"`` estimates its z blur from the image (the workflow's and the CLI's default,
        which :func:`nemo.pipeline.run_frame` applies); None or ``"none"``: not deconvolved.
    deconvolved : (ndarray, dict), optional
        ``volume`` deconvolved by ``psf`` and its record, when already made (the peel reuses it).
    mask_regions : ndarray of int, shape (n, 3), optional
        Voxels (z, y, x) inside the large labels of ``mask`` that touching labels merge
        (:func:`nemo.io.read_mask` ``with_regions``): counted per object as ``regions``, as an
        image's separate bright regions are without a mask.

    Returns
    -------
    meshes : dict
        ``whole`` and, when split, ``inner`` and ``outer`` (trimesh.Trimesh, physical x, y, z).
    resolved : dict
        The section with ``step`` and ``sigma`` as numbers, the iso-level used, the image's
        ``noise``, ``snr``, ``saturated`` and ``background`` (:func:`nemo.surface.image_noise`;
        None with a mask), ``refine_to`` as applied, with ``edge: profile`` ``profile`` (the level
        the walls' fitted profiles gave, or None, the half level, rays and fits), with ``edge: half``
        and an automatic threshold ``edge_check`` (the half level's ``offset`` from the walls'
        profiles, over their contrast; None for textured walls: :func:`nemo.surface.reconstruct`),
        ``deconvolution`` (:func:`nemo.psf.deconvolve`'s record),
        ``n_objects`` (:func:`nemo.surface.find_objects`), ``turned_out`` (objects enclosing the
        dark side, turned out: :func:`nemo.surface.turn_out_dark_objects`), ``walls`` (1 or 2; a list per
        object with ``keep: all`` and several objects), ``regions`` (per analysed object, the
        image's separate bright regions its surface holds, :func:`nemo.surface.regions_per_object`,
        or with a mask the large labels of ``mask_regions``; more than 1: objects meshed as one; None
        when the image has fewer than two regions),
        ``cap_faces`` (faces where the object
        meets the image border: removed with ``border: open``) and the open rim of the analysed
        surface, ``rim_vertices`` and ``rim_loops`` (0 for a closed surface; with ``keep: all`` and
        several objects a list of each object's, so that a closed object beside a cut one is not
        counted as cut), ``largest_hole`` (the length of its longest boundary loop off the image
        border, 0 without one: a wall faded or torn away, judged by the quality control); ``wall_rim_loops``
        and ``wall_largest_hole`` the same for each mesh returned, by name (a wall keeps its own:
        :func:`wall_params`).

    Raises
    ------
    NemoError
        Bad parameters or image (:func:`nemo.surface.reconstruct`); ``keep: all`` with a split
        and no object that has two walls.
    """
    from nemo.geometry import rim
    from nemo.surface import (
        auto_sigma,
        default_mask_sigma,
        default_sigma,
        find_objects,
        image_noise,
        one_object,
        reconstruct,
        regions_per_object,
        turn_out_dark_objects,
    )

    p = nconfig.section("mesh", params)
    shape = (volume if volume is not None else mask).shape
    if p["step"] is None:
        p["step"] = default_step(shape)
    sharp, threshold, raw_objects = _image_to_mesh(volume, spacing, p, check_psf(psf), unit, deconvolved, mask)
    p["sigma_auto"] = None
    if p["sigma"] is None and volume is not None and mask is None:
        p["sigma"], p["sigma_auto"] = auto_sigma(sharp, spacing, p["step"], threshold=threshold)
    elif p["sigma"] is None:  # a mask (or no image): its voxel staircase is what the blur smooths
        p["sigma"] = (default_mask_sigma if mask is not None else default_sigma)(spacing, p["step"])
    whole = reconstruct(sharp, spacing, sigma=float(p["sigma"]), threshold=threshold, mask=mask,
                        step=int(p["step"]), smooth_iter=int(p["smooth"]), keep="all", edge=p["edge"], unit=unit,
                        border=p["border"], refine=bool(p["refine"]), refine_sigma=p["refine_sigma"],
                        refine_to=p["refine_to"], level_offsets=raw_objects["offsets"])
    found = find_objects(whole)  # once: the turn-out check and the choice of objects both need it
    whole, p["turned_out"] = turn_out_dark_objects(whole, found)
    if p["turned_out"]:
        warnings.warn(f"{p['turned_out']} object(s) are dark regions enclosed by a foreground that fills the stack "
                      "around them (a dark object in a bright surround, or a mask's background class): their normals "
                      "are turned to point out of the enclosed region, as for a bright object. If the object is the "
                      "bright surround, give a mask of it; with a probability map, give the object's class",
                      NemoWarning, stacklevel=2)
    surface = whole.metadata["nemo_surface"]
    surface["keep"] = p["keep"]
    if raw_objects["levels"] or raw_objects["peaks"]:  # a deconvolved image meshed at the levels of the one before
        surface.update(object_levels=raw_objects["levels"], region_peaks=raw_objects["peaks"])
    p["level"] = float(surface["level"])
    p["object_levels"] = [float(v) for v in surface.get("object_levels") or []] or None  # own half levels
    p["refine_sigma"] = surface.get("refine_sigma")
    p["refine_to"] = surface.get("refine_to", p["refine_to"])  # level when steepest could not be used
    p["refined"] = {k: surface.get(k) for k in ("refined", "rejected", "shift_median", "shift_abs_p95")}
    if "profile" in surface:  # edge: profile, the walls' fitted profiles (nemo.refine.wall_profile_level)
        p["profile"] = dict(surface["profile"])
    if "edge_check" in surface:  # edge: half, checked against the walls' profiles (nemo.surface._edge_check)
        p["edge_check"] = dict(surface["edge_check"])
    if (p.get("deconvolution") or {}).get("level") is not None:  # the half level, checked on the image as given
        p["edge_check"] = p["deconvolution"].pop("edge_check") or None
    del sharp
    p.update(image_noise(volume, p["level"]) if volume is not None and mask is None
             else {"noise": None, "snr": None, "saturated": None, "background": None})
    if p["snr"] is not None and p["snr"] < QC_MIN_SNR:
        warnings.warn(f"signal-to-noise ratio {p['snr']:.2g} of the segmented channel: the surface is uncertain (a "
                      f"frame below {QC_MIN_SNR:g} is flagged in the summary); check the channel and the time point",
                      NemoWarning, stacklevel=2)
    _check_object_size(whole, spacing, unit, None if mask is not None else volume)
    analysed = found if p["keep"] == "all" else found[:1]
    regions = regions_per_object(whole, analysed, surface.get("region_peaks") or _voxel_points(mask_regions, spacing))
    _warn_joined_regions(regions, from_mask=mask_regions is not None)
    if p["keep"] == "all":  # every object, labelled, each split about its own centre
        meshes = _object_walls(whole, found, p) if len(found) > 1 else _walls(whole, p, centre)
        p["n_objects"] = len(found)
    else:  # several objects: the largest, and a warning
        whole = one_object(whole, p["split"] != "none", p["keep"], objects=found)
        meshes = _walls(whole, p, centre)
        p["n_objects"] = int(whole.metadata["n_objects"])
    p["regions"] = [int(n) for n in regions] if any(regions) else None
    if mask is not None and volume is not None:  # does the mask follow the segmented channel's edges?
        p.update(_mask_fit(meshes["whole"], volume, spacing, unit))
    p["cap_faces"] = int(whole.metadata["nemo_surface"]["cap_faces"])
    info = rim(meshes["whole"].faces, len(meshes["whole"].vertices))  # of the analysed surface
    p["rim_vertices"] = info["n_vertices"]
    if info["n_loops"]:
        logger.info("open surface (cut by the image border): %d rim loop(s), %d rim vertices",
                    info["n_loops"], info["n_vertices"])
    p.update(_wall_openings(meshes, info, len(found) if p["keep"] == "all" and len(found) > 1 else 0))
    stamp_walls(meshes, p)
    return meshes, p


def _wall_openings(meshes: dict[str, trimesh.Trimesh], whole_rim: dict, n_objects: int) -> dict:
    """The mesh step's record of the walls' openings: ``wall_rim_loops`` and ``wall_largest_hole``, each wall's
    own (:func:`_wall_loops`; its holes are its loops beyond the rims: the split opens one round every pore of a
    porous wall, and one round the lip where a wall has faded or torn away), each object's own with
    ``n_objects`` (one beside a cut object is not cut), and the analysed surface's ``rim_loops`` and
    ``largest_hole``; ``whole_rim`` is :func:`nemo.geometry.rim` of ``meshes["whole"]``."""
    border = np.asarray(meshes["whole"].vertices)[whole_rim["vertices"]]  # where the image border cuts it
    openings = {name: _wall_loops(m, n_objects, border) for name, m in meshes.items()}
    return {"wall_rim_loops": {name: rims for name, (rims, _) in openings.items()},
            "wall_largest_hole": {name: hole for name, (_, hole) in openings.items()},
            "rim_loops": openings["whole"][0], "largest_hole": openings["whole"][1]}


def stamp_walls(meshes: dict[str, trimesh.Trimesh], params: dict) -> None:
    """Leave the mesh step's record on each wall, ``metadata["nemo_params"]`` (:func:`wall_params`, each its own
    copy, so a caller's later update of ``params`` stays off it): a saved wall keeps it, and its ``walls`` tell
    the thickness step one-wall objects."""
    for name, m in meshes.items():
        m.metadata["nemo_params"] = dict(wall_params(params, name))


def wall_params(params: dict, name: str) -> dict:
    """The mesh step's record ``params`` as the wall ``name`` (``whole``, ``inner``, ``outer``) keeps it.

    ``rim_loops`` and ``largest_hole`` become that wall's own (``params["wall_rim_loops"]``,
    ``params["wall_largest_hole"]``), so that its boundary loops beyond its rims count as holes, and its
    largest hole is judged against its own area (:func:`nemo.summary.quality_flags`); records without them
    are returned as is.
    """
    own = (params.get("wall_rim_loops") or {}).get(name)
    if own is None:
        return params
    return {**params, "rim_loops": own, "largest_hole": (params.get("wall_largest_hole") or {}).get(name)}


def _wall_loops(mesh: trimesh.Trimesh, n_objects: int, border: np.ndarray) -> tuple:
    """Rim loops and the largest hole of ``mesh`` (one of the analysed surface's walls).

    Its rim loops are its boundary loops through a point of ``border`` (M, 3), the analysed surface's
    rim where the image border cuts it (a wall is a piece of that surface, so its points are the same
    numbers); its holes are its other boundary loops, and the largest hole is the longest one's length
    (mesh unit; 0 without a hole). With ``n_objects`` > 0 each is a list of each object's of the
    labelled mesh, by label.
    """
    from scipy.spatial import cKDTree

    from nemo.geometry import rim

    vertices = np.asarray(mesh.vertices)
    info = rim(mesh.faces, len(vertices))
    on_rim = np.flatnonzero(info["loop"] >= 0)
    at_border = np.zeros(info["n_loops"], dtype=bool)
    if len(on_rim) and len(border):
        tol = 1e-9 * max(float(np.ptp(border, axis=0).max()), 1e-300)  # the same numbers, in any unit
        near = cKDTree(border).query(vertices[on_rim], distance_upper_bound=tol)[0] <= tol
        at_border[info["loop"][on_rim[near]]] = True
    edges = info["edges"]
    lengths = np.bincount(info["loop"][edges[:, 0]], np.linalg.norm(vertices[edges[:, 0]] - vertices[edges[:, 1]], axis=1),
                          minlength=info["n_loops"]) if len(edges) else np.zeros(0)
    holes = np.where(at_border, 0.0, lengths)
    if not n_objects:
        return int(at_border.sum()), float(holes.max(initial=0.0))
    first = np.unique(info["loop"][on_rim], return_index=True)[1]  # a vertex of each loop, loops in order
    label = objects.vertex_labels(mesh)[on_rim[first]] if len(first) else np.zeros(0, dtype=np.int64)
    rims = np.bincount(label[at_border], minlength=n_objects).astype(int).tolist()
    largest = np.zeros(n_objects)
    np.maximum.at(largest, label, holes)
    return rims, largest.tolist()


def _image_to_mesh(volume, spacing, p: dict, psf, unit: str, deconvolved, mask) -> tuple[np.ndarray, str | float, dict]:
    """The image :func:`mesh` meshes, its threshold and the objects' own levels read on the image before
    deconvolution (:func:`nemo.surface.checked_half_level`'s ``objects``): deconvolved by ``psf``
    (:func:`_deconvolved`), except a mask, and the walls' profiles under ``psf: auto`` (meshed as given;
    the layers are still peeled from the deconvolved image). A PSF given as numbers with ``edge: profile``
    is refused."""
    profile = mask is None and p["edge"] == "profile"
    if profile and psf is not None and not is_auto(psf):
        raise NemoError("mesh.edge: profile and a psf do not go together: the deconvolved walls overshoot at their "
                        "edges, so blurred boxes do not fit them (a 4 µm wall read 1.8 µm). Drop the psf, or use "
                        "edge: half (the default; with a psf, the level of the image before deconvolution)")
    if mask is None and (psf is None or meshes_deconvolved(psf, p["edge"])):  # None: _deconvolved's record
        return _deconvolved(volume, spacing, p, psf, unit, deconvolved)
    p["deconvolution"] = _undeconvolved_record(spacing, psf, "a mask: meshed as given" if mask is not None else
                                               "mesh.edge: profile fits blurred boxes to the image's own walls")
    return volume, p["threshold"], _NO_OBJECTS


def _undeconvolved_record(spacing, psf, reason: str) -> dict:
    """The mesh's deconvolution record where the image is meshed as given (a mask, ``edge: profile``):
    nothing deconvolved, the (checked) PSF named (``"auto"``: none estimated, the mesh needs none)."""
    return {**deconvolve(None, spacing, None)[1], "psf": None if psf is None or is_auto(psf) else list(psf),
            "estimated": is_auto(psf), "reason": reason}


#: No objects' own levels from another image (:func:`_image_to_mesh`).
_NO_OBJECTS = {"levels": [], "peaks": [], "offsets": None}


def _deconvolved(volume: np.ndarray, spacing, p: dict, psf, unit: str,
                 deconvolved: tuple[np.ndarray, dict] | None) -> tuple[np.ndarray, str | float, dict]:
    """The image to mesh (deconvolved by ``psf``, :func:`nemo.psf.deconvolve`), its threshold and the
    objects' own levels (:func:`_image_to_mesh`).

    An automatic half level (``edge: half``, the default) is taken on the image **before**
    deconvolution, at its own noise-aware blur, the level it would be meshed at there:
    Richardson-Lucy overshoots at edges and moves a thin wall's plateau peak (measured on 4 µm
    shells under a 2.5 µm z-PSF: levels 121-127 or 35 for 110), while the sharpened edges cross
    the original half level where the object's edge is (thickness 4.06-4.28 µm against 5.07-5.69
    without deconvolution; docs/validation.md, "Deconvolving a known PSF"). The deconvolved image
    is then meshed at that level with its own blur; the level is checked against the walls' profiles and
    corrected as on a frame meshed without deconvolution, and separate objects of different brightness
    keep their own levels, read on that image (:func:`nemo.surface.checked_half_level`: one level lost
    dim objects beside bright ones, or grew the bright ones by 20-50 % in volume, in a review). A numeric
    threshold, or ``edge: threshold``
    (the threshold itself, which ``refine_to: steepest`` must know as such), is applied to the
    deconvolved image. ``p["deconvolution"]`` records the deconvolution and the level.
    """
    from nemo.surface import _check_finite, auto_sigma, checked_half_level, parse_threshold

    if psf is not None:
        _check_finite(volume)  # before the deconvolution's seconds: the mesh step refuses it anyway
        if unit == "pixel" and not is_auto(psf):
            warnings.warn("the image has no calibration (unit pixel): the psf is read in pixels; give "
                          "datasets.NAME.spacing (--spacing) to give the psf in µm", NemoWarning, stacklevel=3)
    sharp, record = deconvolved or deconvolve(volume, spacing, psf)
    p["deconvolution"] = dict(record)  # its own copy: the level below is the mesh's, not the peel's
    threshold = p["threshold"]
    if not p["deconvolution"]["iterations"] or p["edge"] != "half" or not isinstance(parse_threshold(threshold), str):
        return sharp, threshold, _NO_OBJECTS
    sigma = p["sigma"] if p["sigma"] is not None else auto_sigma(volume, spacing, p["step"], threshold=threshold)[0]
    level, check, objects = checked_half_level(volume, spacing, sigma, p["step"], threshold, shift=not p["refine"])
    p["deconvolution"].update(level=level, level_sigma=sigma, edge_check=check)
    return sharp, level, objects


def default_step(shape: tuple[int, ...]) -> int:
    """The marching-cubes step: 1 voxel, 2 for a stack of more than :data:`STEP2_VOXELS` voxels."""
    return 1 if int(np.prod(shape)) <= STEP2_VOXELS else 2


def mask_label_gap(shape: tuple[int, ...], spacing, params: dict | None) -> tuple[int, int, int] | None:
    """With ``mesh.keep: all``, the cut that keeps a label image's touching labels apart
    (:func:`nemo.io.label_gap`, ``read_mask(apart=...)``) for the blur the mesh step will give the
    mask (its ``sigma``, else :func:`nemo.surface.default_mask_sigma` at its step); else None.
    The workflow's ``nemo mesh`` and ``nemo run`` both take it from here."""
    from nemo.io import label_gap
    from nemo.surface import default_mask_sigma

    p = nconfig.section("mesh", params)
    if p["keep"] != "all":
        return None
    sigma = p["sigma"] if p["sigma"] is not None else default_mask_sigma(spacing, p["step"] or default_step(shape))
    return label_gap(spacing, sigma)


def _mask_fit(whole: trimesh.Trimesh, volume: np.ndarray, spacing, unit: str) -> dict:
    """:func:`nemo.surface.mask_edge_offset` of a mask's analysed surface on the segmented channel, each
    object's own (``keep: all``), warned about when the mask holds the darker side or lies off the
    channel's edges (the summary flags it)."""
    from nemo.surface import mask_edge_offset

    fit = mask_edge_offset(whole, volume, spacing, objects.vertex_labels(whole))
    contrast, offset = (np.atleast_1d(np.asarray(fit[k], dtype=np.float64)) for k in ("mask_contrast", "mask_offset"))

    def which(bad: np.ndarray) -> str:  # the objects named when there are several
        return "" if len(contrast) == 1 else f" (object {listed(str(k) for k in np.flatnonzero(bad))})"

    if (contrast < 0).any():
        warnings.warn(f"the mask's inside is darker than its outside in the segmented channel{which(contrast < 0)}: a "
                      "mask of the background or a cavity class? (check mask_channel with a probability map of several "
                      "classes, and segment_channel)", NemoWarning, stacklevel=3)
    off = (offset > fit["mask_offset_limit"]) & ~(contrast < 0)  # a darker inside's edges are not its own
    if off.any():  # another object's than a darker one's
        warnings.warn(f"the mask's surface lies up to {np.nanmax(offset[off]):.3g} {unit} (median) from the segmented "
                      f"channel's own edges{which(off)}, more than "
                      f"{fit['mask_offset_limit']:.3g}: a mask of another time point, channel or class, or a stale "
                      "label? (check the mask's T axis and order, mask_channel and segment_channel)",
                      NemoWarning, stacklevel=3)
    return fit


def _voxel_points(voxels: np.ndarray | None, spacing: tuple[float, float, float]) -> np.ndarray:
    """Voxel indices (n, 3) along z, y, x as physical points (n, 3) x, y, z; (0, 3) for None."""
    if voxels is None:
        return np.empty((0, 3))
    return np.asarray(voxels, dtype=np.float64).reshape(-1, 3)[:, ::-1] * np.asarray(spacing, dtype=np.float64)[::-1]


def _warn_joined_regions(regions: list[int], from_mask: bool = False) -> None:
    """Warn about analysed objects whose surface holds several of the image's separate bright regions
    (``from_mask``: a mask's large labels, which :func:`nemo.io.read_mask` warned about)."""
    joined = [(k, n) for k, n in enumerate(regions) if n > 1]
    if joined and not from_mask:
        warnings.warn("one surface holds several separate bright regions of the image (object: regions "
                      + ", ".join(f"{k}: {n}" for k, n in joined[:10]) + "): touching objects, or objects closer than "
                      "the blur, meshed as one; its area and volume are theirs together (flagged in the summary). "
                      "Give a mask that labels them apart (e.g. Cellpose or StarDist labels)", NemoWarning, stacklevel=3)


def _check_object_size(whole: trimesh.Trimesh, spacing: tuple[float, float, float], unit: str,
                       volume: np.ndarray | None = None) -> None:
    """Refuse a surface whose largest piece is smaller than a voxel (specks selected by a wrong
    threshold or label); the error names isolated hot voxels of ``volume`` (:func:`_hot_voxels`) when
    there are any, the likely specks."""
    from nemo.surface import face_components

    labels = face_components(np.asarray(whole.faces), len(whole.vertices))
    area = float(np.bincount(labels, weights=whole.area_faces).max())
    radius = float(np.sqrt(area / (4 * np.pi)))
    if radius < max(spacing):
        hot = 0 if volume is None else _hot_voxels(volume)
        cause = (f"; {hot} voxel(s) of the image stand far above all their neighbours (a camera's hot pixels?): the "
                 "automatic threshold took them for the object; remove them (e.g. a 3x3x3 median filter) or give "
                 "mesh.threshold" if hot else "")
        raise NemoError(f"the object found is smaller than a voxel (area {area:.3g} {unit}², radius of equal area "
                        f"{radius:.3g} {unit}, voxels up to {max(spacing):.3g} {unit}): no surface to analyse; check the "
                        f"threshold, the mask (and its labels) or the channel{cause}")


def _hot_voxels(volume: np.ndarray) -> int:
    """Voxels (of a (Z, Y, X) image) that exceed every one of their 26 neighbours by more than the image's
    contrast (its 99.9th percentile above its median): no blurred image of an object does that, a camera's
    hot pixel does. Only the voxels above median + contrast are looked at (vectorised over them)."""
    median, top = np.percentile(volume, [50, 99.9])
    contrast = float(top - median)
    candidates = np.flatnonzero(volume > median + contrast)
    if not len(candidates) or contrast <= 0 or len(candidates) > 100_000:  # many: bright structure, not specks
        return 0
    zyx = np.stack(np.unravel_index(candidates, volume.shape), axis=1)
    steps = np.array([d for d in np.ndindex(3, 3, 3) if d != (1, 1, 1)]) - 1
    around = zyx[:, None, :] + steps[None]
    inside = ((around >= 0) & (around < np.array(volume.shape))).all(axis=2)  # beyond the border: no neighbour
    around = np.clip(around, 0, np.array(volume.shape) - 1)
    values = volume[around[..., 0], around[..., 1], around[..., 2]].astype(np.float64)
    brightest = np.where(inside, values, -np.inf).max(axis=1)
    return int(np.count_nonzero(volume.flat[candidates].astype(np.float64) - brightest > contrast))


def _object_walls(whole: trimesh.Trimesh, found: list[dict], p: dict) -> dict[str, trimesh.Trimesh]:
    """Every object of ``whole`` (``keep: all``), labelled (:mod:`nemo.objects`), split if configured."""
    pieces = objects.object_meshes(whole, found)
    unit = getattr(whole, "units", None) or "um"
    logger.info("keeping all %d objects: %s", len(found), listed(
        f"object {k}: area {o['area']:.4g} {unit}², centre ({o['centre'][0]:.4g}, {o['centre'][1]:.4g}, "
        f"{o['centre'][2]:.4g})" for k, o in enumerate(found)))
    _log_left_out(whole, pieces, unit)
    p["walls"] = 1 if p["split"] == "none" else 2
    if p["split"] == "none":
        return {"whole": objects.concatenate(pieces, range(len(pieces)))}
    if p["split"] == "auto":  # each object: split if it has two walls (a loop over objects)
        decided = [_auto_walls(piece, f"object {k}", quiet=len(pieces) > OBJECTS_LOGGED)
                   for k, piece in enumerate(pieces)]
        p["walls"] = [walls for walls, _, _ in decided]
        return objects.split_objects([piece for _, piece, _ in decided], "centre", None, walls=p["walls"],
                                     centres=[centre for _, _, centre in decided])
    meshes = objects.split_objects(pieces, p["split"], p["axis"])
    split = set(objects.vertex_labels(meshes["inner"]).tolist())  # an object of one wall is left out
    p["walls"] = [2 if k in split else 1 for k in range(len(pieces))]
    return meshes


def _log_left_out(whole: trimesh.Trimesh, pieces: list[trimesh.Trimesh], unit: str) -> None:
    """Say which separate surfaces are in no object (below :data:`nemo.surface.OBJECT_MIN_AREA` of the
    largest one's area: noise specks, or a small object among large ones), so none is dropped unseen."""
    from nemo.surface import OBJECT_MIN_AREA, face_components

    used = np.zeros(len(whole.faces), dtype=bool)
    for piece in pieces:  # a loop over objects
        used[piece.metadata["parent_faces"]] = True
    if used.all():
        return
    labels = face_components(np.asarray(whole.faces), len(whole.vertices))
    area = np.bincount(labels[~used], weights=whole.area_faces[~used])
    left = np.flatnonzero(area)
    largest = left[np.argmax(area[left])]
    centre = whole.triangles_center[labels == largest].mean(axis=0)
    logger.info("left out %d surface(s) below %.0f %% of the largest object's area (noise specks, or small objects "
                "among large ones): the largest of them has area %.4g %s² (radius of equal area %.3g %s), centre "
                "(%.4g, %.4g, %.4g)", len(left), 100 * OBJECT_MIN_AREA, area[largest], unit,
                np.sqrt(area[largest] / (4 * np.pi)), unit, *centre)


def _walls(whole: trimesh.Trimesh, p: dict, centre: np.ndarray | None) -> dict[str, trimesh.Trimesh]:
    """``whole`` and, with a split, its ``inner`` and ``outer`` walls (the mesh section ``p``).

    ``split: auto`` splits an object with two walls (:func:`nemo.surface.count_walls`) by its
    centre; an object with one wall gets ``inner`` and ``outer`` equal to ``whole`` (no thickness).
    Sets ``p["walls"]``.
    """
    from nemo.surface import face_components, split_mesh, submesh

    meshes = {"whole": whole}
    p["walls"] = 1 if p["split"] == "none" else 2
    if p["split"] == "auto":
        p["walls"], whole, centre = _auto_walls(whole, "the object", centre)
        if p["walls"] == 1:
            return {"whole": whole, "inner": whole.copy(), "outer": whole.copy()}
    if p["split"] != "none":
        by = "centre" if p["split"] == "auto" else p["split"]
        inner, outer = split_mesh(whole, by=by, axis=p["axis"], centre=centre, keep=p["keep"])
        if p["keep"] == "largest":  # the whole = the components the kept halves came from
            labels = face_components(whole.faces, len(whole.vertices))
            used = np.unique(labels[np.concatenate([inner.metadata["parent_faces"],
                                                    outer.metadata["parent_faces"]])])
            if len(used) < labels.max() + 1:
                meshes["whole"] = submesh(whole, np.isin(labels, used))
        meshes.update(inner=inner, outer=outer)
    return meshes


def _auto_walls(whole: trimesh.Trimesh, what: str, centre: np.ndarray | None = None,
                quiet: bool = False) -> tuple[int, trimesh.Trimesh, np.ndarray | None]:
    """(walls, surface, split centre) of one object under ``split: auto`` (:func:`nemo.surface.count_walls`);
    with one wall, its largest piece (a speck or a small cavity inside it dropped). ``quiet``: its
    verdict in the debug log (one of several objects; :func:`nemo.objects.split_objects` sums them up).

    The centre is ``centre`` (None: the surface's centroid), or for an open object whose pieces
    do not face its centroid, its centre of curvature (:func:`_curvature_centre`): the two faces of
    a gently curved sheet cut by the field of view both face away from a centroid between them.
    """
    from nemo.surface import OBJECT_MIN_AREA, _with_metadata, count_walls, keep_components

    walls, inner, mixed = count_walls(whole, centre)
    curvature_centre = _curvature_centre(whole) if walls == 1 and centre is None else None
    if curvature_centre is not None:
        again = count_walls(whole, curvature_centre)
        if again[0] == 2:
            (walls, inner, _), centre = again, curvature_centre
    say = logger.debug if quiet else logger.info
    if walls == 1 and mixed >= OBJECT_MIN_AREA and _thin_sheet(whole, what, mixed, centre, quiet):
        return 2, whole, centre
    if walls == 2:
        say("split auto: %s has two walls (inner %.0f %% of the outer's area): split by its %s",
            what, 100 * inner, "centre" if centre is None else "centre ({:.4g}, {:.4g}, {:.4g})".format(*centre))
        return 2, whole, centre
    why = (f"its largest surface facing the centre has {100 * inner:.1f} % of the outer's area, below "
           f"{100 * OBJECT_MIN_AREA:.0f} %" if inner else "no separate surface faces its centre")
    if mixed >= OBJECT_MIN_AREA:
        warnings.warn(f"split auto: {what} counts as one wall ({why}), but {100 * mixed:.0f} % of its surface lies in "
                      "pieces that turn partly towards its centre, and it is not a thin sheet round a cavity: a torus, "
                      "a curved cell or a filament has one wall, but a sheet whose two sides meet at a rim (an "
                      "epithelium cut by the image border, a thick-walled torn shell or a shallow cup) has two; set "
                      "split: centre for that", NemoWarning, stacklevel=3)
    say("split auto: %s has one wall (%s): its inner and outer surfaces are the whole surface, and there is "
        "no thickness", what, why)
    return 1, _with_metadata(keep_components(whole, "largest"), whole), None


def _thin_sheet(whole: trimesh.Trimesh, what: str, mixed: float, centre: np.ndarray | None, quiet: bool) -> bool:
    """Whether one surface that turns partly towards its centre is a thin sheet round a cavity, two walls
    joined at a rim or a tear (a shell torn where its wall is thinner than the blur, a cup): its pieces
    that turn so (not a droplet in its lumen) at most :data:`nemo.surface.SHEET_MAX_WIDTH` × its size
    across (:func:`nemo.surface.sheet_width`), flat at that scale, a sheet and not a tube
    (:func:`nemo.surface.sheet_flatness`), and wrapping the centre in at least
    :data:`nemo.surface.CAVITY_MIN_ENCLOSURE` of the directions (:func:`nemo.surface.cavity_enclosure`;
    a thin filled cell does not); warned about when it is (logged with ``quiet``)."""
    from nemo.geometry import surface_centre
    from nemo.surface import (
        CAVITY_MIN_ENCLOSURE,
        SHEET_MAX_WIDTH,
        SHEET_MIN_FLATNESS,
        _face_sides,
        cavity_enclosure,
        sheet_flatness,
        sheet_width,
        submesh,
    )

    _, labels, _, outward, _ = _face_sides(whole, "centre", None, centre)
    turning = np.flatnonzero((outward > 0.1) & (outward < 0.9))
    piece = submesh(whole, np.isin(labels, turning)) if len(turning) else whole  # the sheet's pieces (a cut one has two)
    centre = surface_centre(whole) if centre is None else centre  # count_walls' centre: the whole object's
    width, size = sheet_width(piece), math.sqrt(float(piece.area) / (4 * math.pi))
    if not width <= SHEET_MAX_WIDTH * size:  # NaN: the far side cut away, no width to tell
        return False
    if not sheet_flatness(piece, width) >= SHEET_MIN_FLATNESS or cavity_enclosure(piece, centre) < CAVITY_MIN_ENCLOSURE:
        return False
    unit = getattr(whole, "units", None) or "um"
    message = (f"split auto: {what} is one surface, {100 * mixed:.0f} % of it turning partly towards its centre, "
               f"but a thin sheet ({width:.3g} {unit} across, {100 * width / size:.0f} % of its size) round a cavity: "
               "two walls joined at a rim or a tear (a shell torn where its wall is thinner than the blur, a cup); "
               "split face by face as split: centre does (the tear's holes are counted by the quality control; "
               "split: none keeps one surface)")
    if quiet:
        logger.debug(message)
    else:
        warnings.warn(message, NemoWarning, stacklevel=4)
    return True


def _curvature_centre(whole: trimesh.Trimesh) -> np.ndarray | None:
    """Centre of the sphere fitted to the largest piece of an open surface of several pieces
    (:func:`nemo.surface.fit_sphere`; one face of a sheet: a sphere fitted to both faces of a flat
    slab sits inside it), or, when that is not finite (a plane), a point 10⁶ sizes away against
    that piece's mean normal; None for a closed surface or a single piece."""
    from nemo.geometry import rim
    from nemo.mesh import vertex_normals
    from nemo.surface import face_components, fit_sphere, keep_components

    faces = np.asarray(whole.faces)
    if not len(faces) or not rim(faces, len(whole.vertices))["n_loops"]:
        return None
    if face_components(faces, len(whole.vertices)).max() < 1:
        return None
    piece = keep_components(whole, "largest")
    centre, _ = fit_sphere(piece)
    if np.all(np.isfinite(centre)):
        return centre
    normal = vertex_normals(piece).mean(axis=0)
    size = float(np.ptp(np.asarray(piece.vertices), axis=0).max())
    return piece.centroid - 1e6 * size * normal / max(float(np.linalg.norm(normal)), 1e-300)


#: Mesh units (besides those of :mod:`nemo.io`) a user mesh may be in: voxel indices.
PIXEL_UNITS = ("pixel", "voxel", "px")


def import_mesh(path: str | os.PathLike, volume: np.ndarray | None, spacing: tuple[float, float, float],
                params: dict | None = None, unit: str = "um", mesh_unit: str | None = None,
                centre: np.ndarray | None = None) -> tuple[dict[str, trimesh.Trimesh], dict]:
    """A surface made elsewhere (MeshLab, Blender, ilastik, napari) used instead of meshing.

    The mesh is read (PLY, OBJ or STL; refused if not a manifold surface; turned outward if
    wound inward), converted from ``mesh_unit`` to the image's unit, checked against the image
    (its extent must match the bright object's within ×1.6, :func:`nemo.peel.mesh_object_extent_ratio`)
    and split into walls like a reconstructed surface. Never silently rescaled: a file that
    does not name its unit needs ``mesh_unit``.

    Parameters
    ----------
    path : path-like
        The surface, vertices in physical x, y, z (x = column, y = row, z = plane) of ``mesh_unit``.
    volume : ndarray, shape (Z, Y, X), optional
        The frame's image (None: no extent check).
    spacing : (dz, dy, dx)
        Voxel size in ``unit``.
    params : dict, optional
        The ``mesh`` section (``split``, ``axis``, ``keep``; the meshing keys are unused).
    unit : str
        The image's unit.
    mesh_unit : str, optional
        The mesh's unit (``um``, ``nm``, ``mm`` ..., or ``pixel`` for voxel indices); default:
        the unit the file names (NEMO's PLY).

    Returns
    -------
    meshes : dict
        ``whole`` and, when split, ``inner`` and ``outer``, each with the record in its
        ``metadata["nemo_params"]`` as :func:`mesh` leaves it (its ``walls`` tell the thickness step
        one-wall objects).
    resolved : dict
        The section with ``source``, ``mesh_unit``, ``scale`` (per axis x, y, z), ``extent_ratio``
        and ``n_objects``.

    Raises
    ------
    NemoError
        Unreadable or non-manifold mesh, unknown or missing unit, a mesh that does not cover the
        image's object.
    """
    from nemo.mesh import load_mesh
    from nemo.surface import find_objects

    p = nconfig.section("mesh", params)
    mesh = load_mesh(path)
    given = mesh_unit or (mesh.units if mesh.metadata.get("unit_in_file") else None)
    if given is None:
        raise NemoError(f"{path} does not say in which unit its coordinates are: give it (`mesh_unit`: um, nm, "
                        "mm ..., or pixel for voxel indices x = column, y = row, z = plane)")
    scale = _mesh_scale(given, unit, spacing)
    mesh.vertices = np.asarray(mesh.vertices, dtype=np.float64) * scale
    mesh.units = unit
    ratio = _check_extent(mesh, volume, spacing, path, given) if volume is not None else None
    mesh.metadata["nemo_surface"] = {"method": "imported", "source": str(path)}
    p.update(source=str(path), mesh_unit=given, scale=scale.tolist(), extent_ratio=ratio,
             n_objects=len(find_objects(mesh)), noise=None, snr=None, saturated=None, background=None)
    meshes = _walls(mesh, p, centre)
    stamp_walls(meshes, p)
    return meshes, p


def _mesh_scale(mesh_unit: str, unit: str, spacing) -> np.ndarray:
    """Per-axis (x, y, z) factor from ``mesh_unit`` to ``unit``."""
    from nemo.io import unit_scale

    if mesh_unit.lower() in PIXEL_UNITS:
        return np.asarray(spacing, dtype=np.float64)[::-1]
    if mesh_unit == unit:
        return np.ones(3)
    have, want = unit_scale(mesh_unit), unit_scale(unit)
    if have is None or want is None:
        raise NemoError(f"cannot convert the mesh's unit {mesh_unit!r} to the image's unit {unit!r}: give "
                        "`mesh_unit` as um, nm, mm or pixel, or the image's own unit")
    return np.full(3, have / want)


def _check_extent(mesh: trimesh.Trimesh, volume: np.ndarray, spacing, path, mesh_unit: str) -> float:
    """The mesh's extent over the image object's; outside [1/1.6, 1.6] is an error."""
    from nemo.peel import MAX_EXTENT_RATIO, mesh_object_extent_ratio

    ratio = mesh_object_extent_ratio(mesh, volume, spacing)
    if np.isfinite(ratio) and not 1 / MAX_EXTENT_RATIO <= ratio <= MAX_EXTENT_RATIO:
        raise NemoError(
            f"{path} (read in {mesh_unit}) spans {ratio:.3g} × the extent of the image's bright object: it is "
            "in another unit, scaled or placed elsewhere. Give its unit (`mesh_unit`) and keep its coordinates "
            "in the image's frame (x = column, y = row, z = plane, from the first voxel's centre)")
    return float(ratio) if np.isfinite(ratio) else None


# ----------------------------------------------------------------------------- morphology
def measure(mesh: trimesh.Trimesh, curvature_df: pd.DataFrame | None = None) -> dict:
    """Global morphology of a surface (:func:`nemo.morphology.measure`) with its ``centre``.

    ``centre`` is the area-weighted centroid (x, y, z) of the surface. On a mesh of several
    objects (:mod:`nemo.objects`) ``objects`` holds the same record for each, with its ``object``
    label, so the summary can give each object its own row.
    """
    from nemo.geometry import surface_centre
    from nemo.morphology import measure as measure_surface

    result = measure_surface(mesh, curvature_df)
    result["centre"] = surface_centre(mesh).tolist()
    split = objects.parts(mesh)
    if split:
        result["objects"] = []
        with quiet_objects(len(split), "measure"):
            for part in split:  # a loop over objects
                record = measure(part.mesh, None if curvature_df is None else objects.local_table(curvature_df, part))
                record.pop("walls", None)  # the frame's list, one per object: in the frame's record only
                for key in ("rim_loops", "largest_hole", "mask_offset", "mask_contrast"):  # each object's own
                    record[key] = objects.value_for(record.get(key), part.label)
                result["objects"].append({**record, "object": part.label})
    return result


def curvature_defaults(mesh: trimesh.Trimesh, params: dict | None = None) -> dict:
    """The ``curvature`` section with its radius resolved on ``mesh`` (:func:`nemo.morphology.default_radius`).

    ``radius_from`` records what set a default radius: ``limited_by`` (``stability``: where the
    curvature changes least with the radius; ``size``, ``rim`` or ``edges``: the largest
    radius; ``coverage``: the median distance to an open surface's rim; ``min_edges``), the
    surface's radius of curvature, the mean edge, the rim cap and the pilot's ``ladder`` (each
    radius and the change of the curvature from it to the next).
    """
    from nemo.morphology import default_radius

    split = objects.parts(mesh)
    if split:  # each object its own radius
        with quiet_objects(len(split), "curvature radius"):
            return objects.combine_params([curvature_defaults(part.mesh, params) for part in split], split)
    p = nconfig.section("curvature", params)
    if p["radius"] is None:
        p["radius"], info = default_radius(mesh, fit=p["fit"], rng=int(p["seed"]))
        p["radius_from"] = {k: info[k] for k in ("limited_by", "curvature_radius", "edge", "radius_edges", "rim_cap",
                                                 "ladder")}
    return p


def curvature(mesh: trimesh.Trimesh, params: dict | None = None) -> tuple[pd.DataFrame, dict]:
    """H, K at every vertex (method note §3); default radius: :func:`curvature_defaults`."""
    from nemo.morphology import curvature as fit_curvature

    split = objects.parts(mesh)
    if split:  # each object on its own: no fit reaches across objects
        with quiet_objects(len(split), "curvature"):
            return _combined([curvature(part.mesh, params) for part in split], split)
    p = curvature_defaults(mesh, params)
    df = fit_curvature(mesh, float(p["radius"]), n_samples=p["samples"], fraction=p["fraction"],
                       k_interp=int(p["k_interp"]), rng=int(p["seed"]), fit=p["fit"], smooth=float(p["smooth"]),
                       warn_large=_large_radius_advice(p), local_fraction=float(p["local_fraction"]),
                       adaptive=bool(p["adaptive"]))

    p.update(fit_used=df.attrs.get("fit"), n_fitted=df.attrs.get("n_samples"), local_fits=df.attrs.get("local_fits"),
             fit_scatter_H=df.attrs.get("fit_scatter_H"), fit_scatter_K=df.attrs.get("fit_scatter_K"))
    return df, p


def _large_radius_advice(p: dict) -> str | None:
    """What a "curvature radius is large" warning advises: a smaller radius (the user's), a finer mesh
    (the default at its floor of a few edges), or nothing (a default chosen above its floor)."""
    if "radius_from" not in p:
        return "radius"
    return "mesh" if p["radius_from"]["limited_by"] == "min_edges" else None


def thickness(mesh_from: trimesh.Trimesh, mesh_to: trimesh.Trimesh,
              params: dict | None = None) -> tuple[pd.DataFrame, dict]:
    """Distance from ``mesh_from`` to ``mesh_to`` along the normals (method note §3).

    An object whose two surfaces are the same one (one wall, ``mesh.split: auto``) has no
    thickness: NaN at its vertices, with a warning, and ``one_wall`` (its labels) in the section.
    ``beyond_view`` marks the rays that met nothing because they left the field of view where the
    image's border cut the surface (:func:`nemo.morphology.beyond_view`; their count in the section).
    The distances are then averaged over ``smooth`` mean edges of ``mesh_from``
    (:func:`nemo.morphology.smooth_on_surface`; the width in the mesh unit is the section's
    ``smooth_width``): a noisy wall's roughness makes each ray's distance scatter.
    """
    from nemo.mesh import mean_edge_length
    from nemo.morphology import beyond_view, smooth_on_surface
    from nemo.morphology import thickness as ray_thickness

    p = nconfig.section("thickness", params)
    one_wall, labels = _one_wall(mesh_from, mesh_to, p["direction"])
    p["one_wall"] = labels
    if labels:
        what = "the object has" if labels == [None] else f"object(s) {labels} have"
        warnings.warn(f"{what} one wall (inner and outer surfaces are the same, mesh.split: auto): no thickness "
                      "there (NaN)", NemoWarning, stacklevel=2)
    if one_wall.all():
        d = np.full(len(mesh_from.vertices), np.nan)
    else:
        d = ray_thickness(mesh_from, mesh_to, direction=p["direction"], max_distance=p["max_distance"])
        d[one_wall] = np.nan
    outside = np.zeros(len(d), dtype=bool) if one_wall.all() else beyond_view(
        mesh_from, mesh_to, np.isnan(d) & ~one_wall, p["direction"])
    p["beyond_view"] = int(outside.sum())
    p["smooth_width"] = float(p["smooth"]) * mean_edge_length(mesh_from) if np.isfinite(d).any() else 0.0
    if p["smooth_width"] > 0:
        d = smooth_on_surface(mesh_from, d, p["smooth_width"])[0]  # NaN (no hit, one wall) stays NaN
    df = pd.DataFrame({"vertex": np.arange(len(d), dtype=np.int64), "thickness": d, "beyond_view": outside})
    return _labelled(df, mesh_from), p


def _one_wall(mesh_from: trimesh.Trimesh, mesh_to: trimesh.Trimesh, direction: str) -> tuple[np.ndarray, list]:
    """(per vertex of ``mesh_from``: its object is the same surface in ``mesh_to`` and has one wall,
    those objects' labels; [None] for an unlabelled mesh).

    The mesh step's record (``walls`` in the mesh's ``nemo_params``, as :func:`mesh` leaves it on its
    meshes and the saved walls keep it) says whether an object has one wall; a surface without it
    (another tool's, or ``split: none``, which counts nothing) counts as one wall when it is the same
    surface twice, unless the rays go ``inward`` (a closed shell's whole surface to itself).
    """
    def same(a: trimesh.Trimesh, b: trimesh.Trimesh) -> bool:
        return a.faces.shape == b.faces.shape and a.vertices.shape == b.vertices.shape and bool(
            np.array_equal(a.faces, b.faces) and np.array_equal(a.vertices, b.vertices))

    record = mesh_from.metadata.get("nemo_params") or {}
    walls = None if record.get("split") == "none" else record.get("walls")  # split: none counts no walls

    def one_wall(label: int) -> bool:
        return direction != "inward" if walls is None else objects.value_for(walls, label) == 1

    n = len(mesh_from.vertices)
    parts_from, parts_to = objects.parts(mesh_from), objects.parts(mesh_to)
    if parts_from is None or parts_to is None:
        one = same(mesh_from, mesh_to) and one_wall(0)
        return np.full(n, one), [None] if one else []
    to = {part.label: part.mesh for part in parts_to}
    one = [part for part in parts_from
           if part.label in to and same(part.mesh, to[part.label]) and one_wall(part.label)]  # per object
    mask = np.zeros(n, dtype=bool)
    for part in one:
        mask[part.vertices] = True
    return mask, [part.label for part in one]


# ----------------------------------------------------------------------------- nematics
def peel(
    volume: np.ndarray,
    spacing: tuple[float, float, float],
    mesh: trimesh.Trimesh,
    params: dict,
    shift: np.ndarray | None = None,
    return_profile: bool = False,
    psf: tuple[float, float, float] | str | None = None,
    deconvolved: tuple[np.ndarray, dict] | None = None,
    shift_beyond_view: np.ndarray | None = None,
):
    """One intensity per vertex over a depth range along the normals (method note §4).

    ``params`` is one layer of the ``layers`` section (``range`` required); ``shift`` the
    per-vertex thickness when the layer's ``shift`` fraction is non-zero; ``psf`` the PSF the
    image is deconvolved by first (:func:`nemo.psf.deconvolve`, as :func:`mesh` does), or
    ``deconvolved`` (that volume and its record, already made) is peeled instead;
    ``shift_beyond_view`` (N,) marks the vertices whose shift is NaN because their thickness ray left
    the field of view (the thickness table's ``beyond_view``): their NaN intensity is the view's too.
    Returns the layer table (vertex, intensity, beyond_view: NaN because the samples leave the
    image), the resolved layer (with ``deconvolution``, the deconvolution's record) and, with
    ``return_profile``, the samples and their depths.
    """
    from nemo.mesh import vertex_normals
    from nemo.peel import leaves_image, sample_depths
    from nemo.peel import peel as sample

    p = nconfig.section("layer", params)
    _warn_one_wall_layer(mesh, p)
    normals = vertex_normals(mesh)
    if p["inward"]:
        normals = -normals
    offset = None if shift is None or not p["shift"] else float(p["shift"]) * np.asarray(shift, dtype=np.float64)
    dmin, dmax = (float(v) for v in p["range"])
    volume, record = deconvolved or deconvolve(volume, spacing, psf)
    p["deconvolution"] = dict(record)
    result = sample(volume, spacing, np.asarray(mesh.vertices), normals, dmin, dmax,
                    n_samples=int(p["samples"]), reduce=p["reduce"], interp=p["interp"], shift=offset,
                    return_profile=return_profile)
    intensity = result[0] if return_profile else result
    constant = _constant_layer(intensity)
    if constant:  # kept, so the frame's other steps and summaries go on; directors skip it, the QC flags it
        warnings.warn(f"{constant}; its directors will be skipped", NemoWarning, stacklevel=2)
    _check_texture_depth(volume, spacing, mesh, normals, dmin, dmax, p)
    # NaN where the samples leave the image: on a surface cut by the border, the field of view's (quality control)
    outside = leaves_image(volume.shape, spacing, np.asarray(mesh.vertices), normals,
                           sample_depths(dmin, dmax, int(p["samples"])), offset)
    if offset is not None and shift_beyond_view is not None:
        outside |= np.asarray(shift_beyond_view, dtype=bool) & ~np.isfinite(offset)
    outside &= np.isnan(intensity)
    p["beyond_view"] = int(outside.sum())
    df = _labelled(pd.DataFrame({"vertex": np.arange(len(intensity), dtype=np.int64), "intensity": intensity,
                                 "beyond_view": outside}), mesh)
    return (df, p, result[1], result[2]) if return_profile else (df, p)


def _check_texture_depth(volume: np.ndarray, spacing, mesh: trimesh.Trimesh, normals: np.ndarray, dmin: float,
                         dmax: float, p: dict) -> None:
    """Record where the image's texture peaks around the layer (``p["texture"]``:
    :func:`nemo.peel.texture_profile`) and warn when the peak lies outside the layer's range."""
    from nemo.peel import texture_profile

    prof = texture_profile(volume, spacing, np.asarray(mesh.vertices), normals, dmin, dmax)
    p["texture"] = {k: prof[k] for k in ("peak_depth", "peak", "inside", "outside")}
    if prof["outside"]:
        warnings.warn(f"the image's texture peaks at depth {prof['peak_depth']:.3g} along the normals, outside the "
                      f"layer's range [{dmin:g}, {dmax:g}] ({prof['peak'] / max(prof['inside'], 1e-30):.2g} × the "
                      "strongest within it): the layer may miss the structure it is meant to peel; set its range "
                      "(layers.NAME.range) to include that depth", NemoWarning, stacklevel=3)


def _warn_one_wall_layer(mesh: trimesh.Trimesh, p: dict) -> None:
    """Warn when a layer on the inner or outer wall of an object of one wall reaches out of it."""
    walls = (mesh.metadata.get("nemo_params") or {}).get("walls")
    one = 1 in walls if isinstance(walls, list) else walls == 1
    if one and nconfig.reaches_out_of_one_wall(p):
        warnings.warn(f"the object has one wall (mesh.split: auto), so the layer's {p['surface']} surface is its whole "
                      f"outline and the range {list(p['range'])} reaches outside the object; peel inward "
                      "(inward: true) for a layer under its surface, or set mesh.split: centre for a shell",
                      NemoWarning, stacklevel=3)


def directors_defaults(mesh: trimesh.Trimesh, params: dict | None = None) -> dict:
    """The ``directors`` section with patch radius, pixel and patch count resolved on ``mesh``."""
    from nemo.directors import default_n_patches, default_patch_radius, default_pixel, nominal_radius
    from nemo.mesh import mean_edge_length

    split = objects.parts(mesh)
    if split:  # each object its own patch radius, pixel and patch count
        return objects.combine_params([directors_defaults(part.mesh, params) for part in split], split)
    p = nconfig.section("directors", params)
    edge = mean_edge_length(mesh)
    if p["patch_k"] is not None and params and params.get("patch_radius") is not None:
        raise NemoError("give either directors.patch_radius or directors.patch_k, not both")
    if p["patch_k"] is None:
        if p["patch_radius"] is None:
            p["patch_radius"] = default_patch_radius(mesh)
        nominal = float(p["patch_radius"])
    else:
        p["patch_radius"] = None
        nominal = nominal_radius(mesh, int(p["patch_k"]))
    if p["pixel"] is None:
        p["pixel"] = default_pixel(edge, nominal)
    if p["n_patches"] is None:
        p["n_patches"] = default_n_patches(float(mesh.area), nominal, len(mesh.vertices))
    p["nominal_radius"] = nominal
    return p


def directors(mesh: trimesh.Trimesh, intensity: np.ndarray,
              params: dict | None = None) -> tuple[pd.DataFrame, dict]:
    """Tangential directors at random patch centres (method note §5); the resolved parameters
    also hold ``coherency_noise`` (:func:`nemo.directors.noise_coherency`, the QC's texture floor).

    A layer with one value at every vertex (an empty or all-zero channel), or an object smaller
    than the patch derived from the data (an empty frame's noise specks), has no directors: the
    table is empty and the parameters say why (``skipped``), with a warning, so the frame's later
    steps and the dataset's summaries go on and the quality control flags it. A patch the user
    gave that does not fit the object is an error.
    """
    reason = _constant_layer(intensity)
    if reason is None:
        try:
            return _directors(mesh, intensity, params)
        except ObjectTooSmallError as exc:
            if params and (params.get("patch_radius") is not None or params.get("patch_k") is not None):
                raise  # the user's own patch: theirs to change
            reason = exc.reason
            warnings.warn(f"no directors: {exc}", NemoWarning, stacklevel=2)
    else:
        warnings.warn(f"no directors: {reason}", NemoWarning, stacklevel=2)
    return _no_directors(mesh, params, reason)


def _no_directors(mesh: trimesh.Trimesh, params: dict | None, reason: str) -> tuple[pd.DataFrame, dict]:
    """The empty directors table of a layer (or object) that has none, its parameters saying why
    (``skipped``, also in each object's record, which the summary reads)."""
    empty = pd.DataFrame({c: np.zeros(0, np.int64 if c == "vertex" else np.float64) for c in SCHEMAS["directors"]})
    p = {**directors_defaults(mesh, params), "skipped": reason}
    if p.get("objects"):
        p["objects"] = [{**o, "skipped": reason} for o in p["objects"]]
    return _labelled(empty, mesh), p


def _constant_layer(intensity: np.ndarray) -> str | None:
    """Why a layer has nothing to orient (one value at every vertex that has one), or None."""
    seen = np.asarray(intensity, dtype=np.float64)
    seen = seen[np.isfinite(seen)]
    if seen.size and seen.min() == seen.max():
        return (f"the layer's intensity is {seen[0]:g} at every vertex (an empty or all-zero channel, or a mesh "
                "off the object: check the channel with `nemo info FILE`, or leave it out)")
    return None


def _directors(mesh: trimesh.Trimesh, intensity: np.ndarray, params: dict | None) -> tuple[pd.DataFrame, dict]:
    """:func:`directors` of a layer that has texture; raises :class:`ObjectTooSmallError` when no
    object fits the patch."""
    from nemo.directors import directors as measure_directors
    from nemo.directors import noise_coherency

    split = objects.parts(mesh)
    if split:  # patches never reach across objects; an object smaller than its patch gets none
        intensity = np.asarray(intensity)
        with quiet_objects(len(split), "directors"):
            results = _each_object(split, lambda k, part: _directors(part.mesh, intensity[part.vertices], params),
                                   "directors")
        empty = next(r for r in results if not isinstance(r, str))[0].iloc[:0]
        return _combined([(empty, {"skipped": r}) if isinstance(r, str) else r for r in results], split)
    constant = _constant_layer(intensity)
    if constant:  # one object of several, on a layer constant there: left out like an object too small
        raise ObjectTooSmallError(constant, reason=constant)
    p = directors_defaults(mesh, params)
    if not params or (params.get("patch_radius") is None and params.get("patch_k") is None):
        _check_default_patch(mesh, float(p["patch_radius"]))
    settings = {"patch_radius": p["patch_radius"], "patch_k": p["patch_k"], "pixel": float(p["pixel"]),
                "sigma": p["sigma"], "frames": p["frames"]}
    if p["sigma"] is None:  # noise-aware: measured at SIGMA_PX, again wider where those directors are noisy
        df, p["sigma"], p["sigma_auto"] = _noise_aware_directors(mesh, intensity, p, settings)
        settings["sigma"] = p["sigma"]
    else:
        df = measure_directors(mesh, intensity, n_patches=int(p["n_patches"]), rng=int(p["seed"]), **settings)
    p["coherency_noise"] = noise_coherency(mesh, rng=int(p["seed"]), **settings)  # the QC's texture floor
    return df, p


def _noise_aware_directors(mesh: trimesh.Trimesh, intensity: np.ndarray, p: dict,
                           settings: dict) -> tuple[pd.DataFrame, float, dict]:
    """Directors at :data:`nemo.directors.SIGMA_PX`, measured again at
    :func:`nemo.directors.noise_aware_sigma` of their own noise (:func:`nemo.directors.director_noise`)
    where that is wider: the table, the scale (pixels) and its record."""
    from nemo.directors import SIGMA_PX, director_noise, noise_aware_max_px, noise_aware_sigma
    from nemo.directors import directors as measure_directors
    from nemo.mesh import mean_edge_length, vertex_normals

    def measure(sigma: float) -> pd.DataFrame:
        return measure_directors(mesh, intensity, n_patches=int(p["n_patches"]), rng=int(p["seed"]),
                                 **{**settings, "sigma": sigma})

    df = measure(SIGMA_PX)
    normals = vertex_normals(mesh)[df["vertex"].to_numpy(dtype=np.int64)]
    noise, n_pairs = director_noise(df, SIGMA_PX * float(p["pixel"]), normals)
    sigma = noise_aware_sigma(noise, noise_aware_max_px(mean_edge_length(mesh), float(p["pixel"])))
    record = {"noise_deg": None if math.isnan(noise) else round(noise, 3), "pairs": n_pairs, "first_sigma": SIGMA_PX}
    if sigma > SIGMA_PX:
        logger.info("directors: noise %.1f° at σ %g px: measured again at σ %.3g px", noise, SIGMA_PX, sigma)
        df = measure(sigma)
    return df, float(sigma), record


def _check_default_patch(mesh: trimesh.Trimesh, patch_radius: float) -> None:
    """Refuse an object smaller than the default patch, naming what set it (the object's size or its
    mesh's edges) and the likely cause; :func:`nemo.directors.check_patch_size` advises on a given one."""
    from nemo.directors import PATCH_MIN_EDGES, PATCH_PER_RADIUS
    from nemo.mesh import mean_edge_length, object_radius

    size = object_radius(mesh)
    if patch_radius <= size:
        return
    raise ObjectTooSmallError(
        f"the object (radius {size:.4g} from its area) is smaller than the directors' default patch (radius "
        f"{patch_radius:.4g}: the larger of {PATCH_PER_RADIUS:g} × the object's radius and {PATCH_MIN_EDGES:g} mean "
        f"edges of {mean_edge_length(mesh):.3g}): a surface a few edges across has no texture to orient. An empty "
        "frame, or one whose object left the field, meshes noise specks (its SNR is low): check the time point "
        "and the segmented channel, or leave the frame out; a small object needs a finer mesh (mesh.step 1, a "
        "smaller mesh.sigma)",
        reason=f"the object (radius {size:.3g}) is smaller than the default directors' patch ({patch_radius:.3g})")


def import_directors(mesh: trimesh.Trimesh, points: pd.DataFrame, params: dict | None = None,
                     source: str = "the points") -> tuple[pd.DataFrame, dict]:
    """Directors from another tool, mapped onto ``mesh`` (``nemo directors import``).

    ``params`` is the ``directors_import`` section: ``max_distance`` defaults to 2 mean edge
    lengths. The result records ``nominal_radius`` such that ``order.radius`` (2.5 × it) defaults
    to the disc holding about ``IMPORTED_PER_DISC`` = 10 imported directors (1.78 × their spacing:
    other tools' fields are often one director per cell or grid point); and the counts of
    :func:`nemo.import_directors.import_directors` (points, far, nearly normal, directors).

    Returns
    -------
    directors : DataFrame, shape (M, 8)
    resolved : dict
    """
    from nemo.import_directors import MAX_DISTANCE_EDGES
    from nemo.import_directors import import_directors as map_directors
    from nemo.mesh import mean_edge_length

    p = nconfig.section("directors_import", params)
    if p["max_distance"] is None:
        p["max_distance"] = MAX_DISTANCE_EDGES * mean_edge_length(mesh)
    df, counts = map_directors(mesh, points, basis=p["basis"], axis=p["axis"], angle_unit=p["angle_unit"],
                               max_distance=float(p["max_distance"]), min_tangential=float(p["min_tangential"]),
                               source=source)
    # the order radius defaults to ORDER_PER_PATCH × nominal_radius: make it the disc holding about
    # IMPORTED_PER_DISC directors (1.78 × their spacing; Eckert et al. 2025 average over 1.7 × the grid)
    spacing = float(np.sqrt(float(mesh.area) / max(len(df), 1)))
    p["nominal_radius"] = float(np.sqrt(IMPORTED_PER_DISC / np.pi) * spacing / ORDER_PER_PATCH)
    p.update(counts)
    df = _labelled(df, mesh)
    logger.info("directors import: %d points -> %d directors (%d far, %d nearly normal)", counts["n_points"],
                counts["n_directors"], counts["n_far"], counts["n_nearly_normal"])
    return df, p


def order(mesh: trimesh.Trimesh, directors_df: pd.DataFrame, params: dict | None = None,
          patch_radius: float | None = None) -> tuple[pd.DataFrame, dict]:
    """S and the averaged director (method note §6); radius default 2.5 × the patch radius.

    ``patch_radius`` is the directors' (nominal) patch radius, needed only for the default (one
    per object, :func:`nemo.objects.values`, on a mesh of several objects).
    ``weights`` (``none`` = the paper's plain mean, the default, or ``coherency``) is kept in the resolved
    parameters, so the order table's provenance records it.
    """
    from nemo.order import no_order
    from nemo.order import order as q_average

    split = objects.parts(mesh)
    if not len(directors_df):  # no directors (``directors``' skipped frames): no order anywhere
        return _labelled(no_order(mesh.vertices), mesh), {**nconfig.section("order", params), "skipped": NO_DIRECTORS}
    if split:  # each object's directors averaged on it alone; patch_radius: one or one per object
        local = [objects.local_table(directors_df, part) for part in split]
        with quiet_objects(len(split), "order"):
            results = [None if not len(d) else order(part.mesh, d, params, objects.value_for(patch_radius, k))
                       for k, (part, d) in enumerate(zip(split, local))]
        return _combined([r if r is not None else (no_order(part.mesh.vertices), {"skipped": NO_DIRECTORS})
                          for r, part in zip(results, split)], split)
    p = nconfig.section("order", params)
    if p["radius"] is None:
        if not patch_radius:
            raise NemoError("order.radius is not given and the directors' patch radius is unknown: "
                            "give the averaging radius (e.g. 2.5 × the patch radius)")
        p["radius"] = ORDER_PER_PATCH * float(patch_radius)
        _warn_wide_average(mesh, p["radius"])
    return q_average(mesh, directors_df, float(p["radius"]), targets=p["targets"], weights=p["weights"]), p


#: A default averaging radius above this fraction of the object's radius is warned about.
WIDE_AVERAGE = 0.5


def _warn_wide_average(mesh: trimesh.Trimesh, radius: float) -> None:
    """Warn when the default averaging radius spans much of a small object (its patch radius at the
    floor of :data:`nemo.directors.PATCH_MIN_EDGES` edges): S is then averaged over a good part of
    the surface, low-S caps widen, and a +1 may read as two +½ far apart (an independent review:
    23 µm on shells of R 13–26 µm)."""
    from nemo.directors import PATCH_MIN_EDGES

    size = object_radius(mesh)
    if radius > WIDE_AVERAGE * size:
        warnings.warn(f"the default averaging radius {radius:.3g} is {radius / size:.2g} × the object's radius "
                      f"{size:.3g} (of the sphere of its area; {ORDER_PER_PATCH:g} × the directors' patch, at least "
                      f"{PATCH_MIN_EDGES:g} mesh "
                      "edges): S is averaged over much of the object and its defects' positions and charges are "
                      "uncertain; a finer mesh (smaller voxels or mesh.step) or a smaller order.radius helps",
                      NemoWarning, stacklevel=3)


def defects(
    mesh: trimesh.Trimesh,
    order_df: pd.DataFrame,
    directors_df: pd.DataFrame,
    params: dict | None = None,
    avg_radius: float | None = None,
    curvature: np.ndarray | None = None,
    intensity: np.ndarray | None = None,
    director_params: dict | None = None,
) -> tuple[pd.DataFrame, pd.DataFrame | None, dict]:
    """Defects and their curvature-corrected charges, with the refinement pass (method note §7).

    Parameters
    ----------
    avg_radius : float or list of float, optional
        The order table's averaging radius (estimated from S when None); one per object on a mesh
        of several objects (:func:`nemo.objects.values`), each searched on its own.
    curvature : ndarray, shape (N,), optional
        Per-vertex K, used when ``defects.curvature_source`` is ``table``.
    intensity, director_params : optional
        The peeled layer and the directors' resolved parameters: with both, and
        ``refine_directors > 0``, extra directors are measured near each first-pass defect and
        the defects found again.

    Returns
    -------
    defects : DataFrame
    extra : DataFrame or None
        The refinement directors (None without a refinement pass).
    resolved : dict
        The section with the thresholds and radii used (``find_defects``'s parameters) and
        ``topology_search``: on a closed surface whose charges do not sum to χ (a missed
        defect), the search is repeated with the candidate threshold relaxed by
        :data:`TOPOLOGY_THRESHOLD_STEPS` (unless ``s_threshold`` was given) and the result
        closest to χ kept; ``passes`` and ``relaxed_s_threshold`` (None: the first pass) say
        what happened. A frame that still misses χ is flagged by the summary's quality control,
        as is one with ``rejected_zeros`` (:func:`nemo.defects.rejected_zeros`: zeros of the
        averaged Q-tensor rejected for their contour: possibly missed defects).
    """
    p = nconfig.section("defects", params)
    if p["curvature_source"] == "table" and p["curvature_correction"] and curvature is None:
        raise NemoError("defects.curvature_source is 'table' but no curvature table was given")
    split = objects.parts(mesh)
    if not len(directors_df):  # no directors (``directors``' skipped frames): nothing to search
        return _no_defects(mesh, None, params, NO_DIRECTORS)
    if split:
        return _defects_by_object(split, order_df, directors_df, params, avg_radius, curvature, intensity,
                                  director_params)
    try:
        return _defects_one(mesh, order_df, directors_df, params, avg_radius, curvature, intensity, director_params)
    except ObjectTooSmallError as exc:
        if p["contour_radius"] is not None:
            raise  # the user's own radius: theirs to change
        # a radius derived from the data (the averaging radius): the morphology of a small object is still wanted
        return _no_defects(mesh, None, params, f"the object is too small for the lengths derived from the data: "
                                               f"{exc.reason}")


def _defects_one(mesh, order_df, directors_df, params, avg_radius, curvature, intensity, director_params):
    """:func:`defects` on a mesh of one object."""
    p = nconfig.section("defects", params)
    source = p["curvature_source"]
    if source == "table" and curvature is None:  # no K term at all (curvature_correction off)
        source = "angle-defects"
    kwargs = dict(
        curvature=curvature if source == "table" else None, curvature_source=source,
        s_threshold=p["s_threshold"], min_distance=p["min_distance"], max_defects=p["max_defects"],
        contour_radius=p["contour_radius"], curvature_correction=bool(p["curvature_correction"]),
        avg_radius=avg_radius, winding_field=p["winding_field"], refine=p["refine"],
    )
    args = (mesh, order_df, directors_df, p, intensity, director_params)
    df, extra = _find_and_refine(*args, kwargs)
    search = {"passes": 1, "relaxed_s_threshold": None}
    if p["s_threshold"] is None and _topology_mismatch(df) > TOPOLOGY_TOLERANCE:
        base = float(df.attrs["parameters"]["s_threshold"])  # the factors apply to the first pass's threshold
        for factor in TOPOLOGY_THRESHOLD_STEPS:  # a missed defect: its S dip was above the threshold
            relaxed = dict(kwargs, s_threshold=factor * base)
            with warnings.catch_warnings():  # the user set no threshold: "lower s_threshold" is not theirs to act on
                warnings.filterwarnings("ignore", message="the contour of a defect must reach", category=NemoWarning)
                again, extra_again = _find_and_refine(*args, relaxed)
            search["passes"] += 1
            if _topology_mismatch(again) < _topology_mismatch(df):
                df, extra, search["relaxed_s_threshold"] = again, extra_again, relaxed["s_threshold"]
            if _topology_mismatch(df) <= TOPOLOGY_TOLERANCE:
                break
    p["topology_search"] = search
    found = df.attrs["parameters"]
    p.update({k: found[k] for k in ("s_threshold", "min_distance", "contour_radius", "avg_radius", "fit_radius",
                                    "rejected_zeros") if k in found})
    p["n_refine_directors"] = 0 if extra is None else int(len(extra))
    logger.info("defects: %d found (Σ charge %.3f, χ = %s)", len(df), df.attrs["euler_check"]["sum_charge"],
                df.attrs["euler_check"]["euler_characteristic"])
    if p.get("rejected_zeros"):
        logger.warning("defects: %d zero(s) of the averaged order rejected for their contour (disordered, an "
                       "unresolved winding, or a zero charge round them): defects closer together than the contour "
                       "radius may be missed there (the summary flags the frame)", p["rejected_zeros"])
    return df, extra, p


def _defects_by_object(split, order_df, directors_df, params, avg_radius, curvature, intensity, director_params):
    """:func:`defects` on each object of a labelled mesh; one table, Euler checks per object and summed."""
    found, extras, resolved, errors = [], [], [], []
    with quiet_objects(len(split), "defects"):
        for k, part in enumerate(split):  # a loop over objects
            v = part.vertices
            local = objects.local_table(directors_df, part)
            try:
                if not len(local):
                    raise ObjectTooSmallError(NO_DIRECTORS)
                df, extra, p = defects(part.mesh, objects.local_table(order_df, part), local, params,
                                       objects.value_for(avg_radius, k), None if curvature is None else curvature[v],
                                       None if intensity is None else np.asarray(intensity)[v],
                                       objects.pick(director_params, k))
            except ObjectTooSmallError as exc:  # e.g. an object smaller than its averaging radius: the others go on
                errors.append(exc)
                df, extra, p = _no_defects(part.mesh, part.label, params, str(exc))
            found.append(df)
            extras.append(extra)
            resolved.append(p)
    if len(errors) == len(split):  # no object could be searched: as for a single object, an error
        raise errors[0]
    out = objects.combine_tables(found, split, sort=False)
    checks = [df.attrs["euler_check"] for df in found]
    out.attrs["euler_check"] = {
        "sum_charge": float(sum(c["sum_charge"] for c in checks)),
        "sum_charge_rounded": float(sum(c["sum_charge_rounded"] for c in checks)),
        "euler_characteristic": int(sum(c["euler_characteristic"] for c in checks)),
        "closed": all(c["closed"] for c in checks), "matches": all(c["matches"] for c in checks),
        "objects": [dict(c, object=part.label) for c, part in zip(checks, split)],
    }
    out.attrs["parameters"] = objects.combine_params([df.attrs["parameters"] for df in found], split)
    out.attrs["candidates"] = [dict(r, object=part.label, vertex=int(part.vertices[int(r["vertex"])]))
                               for df, part in zip(found, split) for r in df.attrs.get("candidates", [])]
    pieces = [(e, part) for e, part in zip(extras, split) if e is not None]
    extra = objects.combine_tables([e for e, _ in pieces], [q for _, q in pieces], sort=False) if pieces else None
    resolved = objects.combine_params(resolved, split)
    counts = [o.get("rejected_zeros") for o in resolved["objects"] if o.get("rejected_zeros") is not None]
    resolved["rejected_zeros"] = sum(counts) if counts else None  # the frame's, not the first object's
    return out, extra, resolved


def _no_defects(mesh: trimesh.Trimesh, label, params: dict | None, reason: str) -> tuple[pd.DataFrame, None, dict]:
    """The empty result of an object (``label``; None for the only one) whose defect search cannot
    run, with a warning naming why."""
    import warnings

    from nemo.defects import COLUMNS
    from nemo.errors import NemoWarning

    what = "" if label is None else f"object {label}: "
    warnings.warn(f"{what}no defect search ({reason})", NemoWarning, stacklevel=3)
    df = pd.DataFrame(columns=list(COLUMNS))
    df.attrs["euler_check"] = {"sum_charge": 0.0, "sum_charge_rounded": 0.0, "closed": bool(mesh.is_watertight),
                               "euler_characteristic": int(mesh.euler_number), "matches": False,
                               "skipped": reason}
    df.attrs["parameters"] = {"skipped": reason}
    df.attrs["candidates"] = []  # none examined (`nemo defects --candidates` writes an empty table)
    return df, None, {**nconfig.section("defects", params), "skipped": reason}


def _combined(results: list[tuple[pd.DataFrame, dict]], split: list) -> tuple[pd.DataFrame, dict]:
    """One table and one resolved record from a step's per-object results (:mod:`nemo.objects`)."""
    return (objects.combine_tables([df for df, _ in results], split),
            objects.combine_params([p for _, p in results], split))


def _labelled(df: pd.DataFrame, mesh: trimesh.Trimesh) -> pd.DataFrame:
    """``df`` with the ``object`` column when ``mesh`` is labelled (:mod:`nemo.objects`; else as is)."""
    return objects.with_object(df, objects.vertex_labels(mesh)) if objects.labelled(mesh) else df


#: Why an object of a labelled mesh has no order value and no defect search.
NO_DIRECTORS = "no director on this object (smaller than the director patch, or a layer without texture)"


def _each_object(split: list, run_one, what: str) -> list:
    """``run_one(k, part)`` for every object; an object too small for the step gives the reason instead.

    A warning names each object left out; when every object is too small, the first error is raised.
    """
    import warnings

    from nemo.errors import NemoWarning

    out, errors = [], []
    for k, part in enumerate(split):  # a loop over objects
        try:
            out.append(run_one(k, part))
        except ObjectTooSmallError as exc:
            warnings.warn(f"object {part.label}: no {what} ({exc})", NemoWarning, stacklevel=3)
            out.append(exc.reason)  # the short reason, for the object's quality flag
            errors.append(exc)
    if len(errors) == len(split):
        raise errors[0]
    return out


#: Largest |Σ charge − χ| of a closed surface's defects accepted without a second search (a
#: missed or spurious ±½ defect changes the sum by 0.5).
TOPOLOGY_TOLERANCE = 0.25
#: Factors on the candidate threshold tried, in turn, when the charges do not sum to χ.
TOPOLOGY_THRESHOLD_STEPS = (1.5, 2.0)


def _topology_mismatch(df: pd.DataFrame) -> float:
    """|Σ charge − χ| on a closed surface; 0 on an open one (no constraint there)."""
    check = df.attrs["euler_check"]
    return abs(check["sum_charge"] - check["euler_characteristic"]) if check["closed"] else 0.0


def _find_and_refine(mesh, order_df, directors_df, p, intensity, director_params, kwargs):
    """One defect search: :func:`nemo.defects.find_defects`, then the refinement-director pass."""
    from nemo.defects import find_defects, refine_with_directors

    df = find_defects(mesh, order_df, directors_df, **kwargs)
    refine = (p["refine_directors"] > 0 and p["refine"] == "model" and len(df)
              and intensity is not None and director_params is not None)
    if not refine:
        return df, None
    return refine_with_directors(mesh, df, order_df, directors_df, intensity, director_params,
                                 fraction=float(p["refine_directors"]), seed=int(director_params.get("seed", 0)),
                                 **kwargs)


def tracking_distance(params: dict | None, defects_params: list[dict], n_defects: int | None = None) -> dict:
    """The ``tracking`` section with ``max_distance`` resolved: the defects' suppression radius.

    Two defects of one layer are at least ``defects.min_distance`` apart in a frame, so a link
    shorter than that is unambiguous. ``defects_params`` are the defects tables' parameters.
    """
    p = nconfig.section("tracking", params)
    if p["max_distance"] is None:
        values = [float(d["min_distance"]) for d in defects_params if d.get("min_distance")]
        if not values and n_defects == 0:
            values = [1.0]  # nothing to link: any distance gives the same (empty) tracks
        if not values:
            raise NemoError("tracking.max_distance is not given and no defects table records its "
                            "min_distance: give tracking.max_distance")
        p["max_distance"] = float(np.median(values))
    return p

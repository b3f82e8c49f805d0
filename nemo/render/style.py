"""How figures read: field labels with units, colour maps, colour limits, captions, line styles.

Every figure of :mod:`nemo.render` (pyvista renders, matplotlib figures) and the napari layers
take their labels, colour maps and colour ranges from here, so that one field looks the same
everywhere: S viridis on [0, 1], curvatures on a diverging map symmetric about 0 (red
positive), charges bwr on [−1, 1]. :data:`CAPTIONS` holds the caption of each figure kind
(written to ``figures.json`` and shown in the workflow report).

numpy only; no plotting library is imported here.
"""

from __future__ import annotations

import numpy as np

# --------------------------------------------------------------------------------------------
# labels, captions

#: Colour-bar label of each field kind (``{unit}`` is the mesh's unit, normally µm).
FIELD_LABELS: dict[str, str] = {
    "intensity": "intensity [a.u.]",
    "S": "S",
    "coherency": "coherency",
    "H": "H [1/{unit}]",
    "K": "K [1/{unit}²]",
    "k1": "k1 [1/{unit}]",
    "k2": "k2 [1/{unit}]",
    "thickness": "thickness [{unit}]",
    "c": "alignment c = cos 2Δθ",
    "charge": "charge m",
    "t": "time point t",
}


#: Default colour map of each field kind.
FIELD_CMAPS: dict[str, str] = {
    "intensity": "gray", "S": "viridis", "coherency": "viridis", "H": "RdBu_r", "K": "RdBu_r",
    "k1": "RdBu_r", "k2": "RdBu_r", "thickness": "magma", "c": "coolwarm", "charge": "bwr",
}


#: Caption of each figure kind; ``{layer}``, ``{surface}``, ``{a}``, ``{b}`` are filled in.
CAPTIONS: dict[str, str] = {
    "surface_intensity": (
        "Layer {layer}: peeled intensity [a.u.] on the {surface} surface, two opposite views. "
        "Each vertex carries the image sampled along its outward normal over the layer's depth "
        "range and reduced to one value (the 'projection of an intensity layer')."
    ),
    "surface_order": (
        "Layer {layer}: nematic order S of the tangential Q-tensor average on the {surface} "
        "surface, with the averaged directors n_avg drawn as headless segments coloured by S "
        "(one per surface cell of the glyph spacing). Low S marks disorder and defect cores."
    ),
    "surface_defects": (
        "Layer {layer}: topological defects on the {surface} surface (grey: peeled intensity). "
        "Markers are coloured by the curvature-corrected charge m (blue negative, red positive) "
        "and labelled with the charge rounded to the nearest half."
    ),
    "distributions": (
        "Layer {layer}: probability density of the nematic order S over all surface vertices "
        "(left) and of the defect charges m (right; dashed lines at ±1/2), as in the paper's "
        "Fig. 2C."
    ),
    "spherical": (
        "Layer {layer}: the surface in spherical coordinates around its centroid (azimuth φ "
        "from +x towards +y, polar angle θ from +z), as in the paper's Fig. 2D. Background: "
        "peeled intensity; segments: averaged directors coloured by S; circles: defects coloured "
        "by charge. Near the poles the map stretches in φ."
    ),
    "surface_H": "Mean curvature H [1/µm] on the {surface} surface (outward normals: a sphere "
                 "of radius R has H = +1/R), two opposite views.",
    "surface_K": "Gaussian curvature K [1/µm²] on the {surface} surface (sphere: K = 1/R²; "
                 "saddles negative), two opposite views.",
    "surface_thickness": "Thickness [µm] from the {surface} surface to the opposite surface "
                         "along the vertex normals; grey where the ray found no surface (NaN).",
    "morphology_map": "Morphology of the {surface} surface in spherical coordinates around "
                      "its centroid: mean curvature H [1/µm], Gaussian curvature K [1/µm²] and "
                      "thickness [µm] (where computed).",
    "alignment": (
        "Inter-layer alignment between layers {a} and {b}: c = cos 2(θ_b − θ_a) at each "
        "director of {a} with the nearest director of {b} (1 parallel, −1 orthogonal), in "
        "spherical coordinates (left) and as a histogram with its mean (right)."
    ),
    "tracks": (
        "Layer {layer}: defect tracks over time in spherical coordinates around the surface "
        "centroid (left; one colour per track, label = track id and charge) and the distance "
        "travelled from each track's first position along the surface (right)."
    ),
    "defect_map": (
        "Layer {layer}: the defects of every frame on an equal-area (Mollweide) map around the "
        "surface centroid (longitude = azimuth φ from +x towards +y, latitude = 90° − θ, north "
        "= +z). Colour: charge m on a diverging scale centred on 0 (red positive, blue "
        "negative); shape: circle m > 0, triangle m < 0; earlier frames fainter, the last frame "
        "with bold edges; grey lines join the positions of one track."
    ),
    "frames": (
        "Per-frame summary over time t. Top row, per layer (one colour per channel and layer): "
        "nematic order S (mean solid, median dashed; 0–1), number of defects, and their total "
        "charge Σm with the surface's Euler characteristic χ as dashed reference (Poincaré–Hopf: "
        "Σm = χ on a closed surface; grey band ±0.25). Second row, per surface: wall thickness "
        "(mean, median), mean curvature H (mesh and fit), area and enclosed volume. Morphology "
        "axes span at least ±5 % of the mean, so numerical noise looks flat. Bottom: quality "
        "control per frame (green pass, red ✕ flagged; flagged t shaded red in every panel) "
        "with the reasons."
    ),
}


def caption(kind: str, **names) -> str:
    """The caption of a figure kind with its names filled in (missing names stay readable)."""

    class _Keep(dict):
        def __missing__(self, key):
            return key

    return CAPTIONS[kind].format_map(_Keep(**{k: v for k, v in names.items() if v is not None}))


def field_label(kind: str, unit: str = "um") -> str:
    """Colour-bar label of a field kind with its physical unit (``"um"`` shown as µm)."""
    return FIELD_LABELS.get(kind, kind).replace("{unit}", unit_text(unit))


def charge_text(q: float) -> str:
    """A charge rounded to the nearest half as text: ``+1/2``, ``-1/2``, ``+1``, ``0``."""
    if not np.isfinite(q):
        return "?"
    half = round(2 * float(q))
    if half == 0:
        return "0"
    sign = "+" if half > 0 else "-"
    return f"{sign}{abs(half)}/2" if half % 2 else f"{sign}{abs(half) // 2}"


def unit_text(unit: str) -> str:
    """A length unit as shown in labels: ``"um"`` (or ``"micron"``) -> ``"µm"``."""
    return "µm" if unit in ("um", "µm", "micron") else unit


# --------------------------------------------------------------------------------------------
# colour limits and line styles

#: Field kinds whose sign matters: diverging colour maps with limits symmetric about 0.
SIGNED_KINDS = ("H", "K", "k1", "k2")


def robust_limits(values: np.ndarray, kind: str = "") -> tuple[float, float]:
    """Colour limits of a field kind.

    Parameters
    ----------
    values : ndarray
        The field (NaN ignored).
    kind : str
        Field kind (:data:`FIELD_LABELS` key).

    Returns
    -------
    (lo, hi) : tuple of float
        Fixed for S [0, 1], alignment c and charge [−1, 1]. Curvatures (:data:`SIGNED_KINDS`,
        diverging maps) are symmetric about 0, ±(99th percentile of |value|) rounded up to a
        round number (so the colour-bar ticks ±m, ±m/2 read well), whatever the data: white is
        always 0, red always positive (convex with outward normals), blue always negative -- an
        all-positive sphere is uniformly red, never half blue. Other fields: the
        1--99 % range.
    """
    if kind == "S":
        return 0.0, 1.0
    if kind in ("c", "charge"):
        return -1.0, 1.0
    v = np.asarray(values, dtype=np.float64)
    v = v[np.isfinite(v)]
    if v.size == 0:
        return (-1.0, 1.0) if kind in SIGNED_KINDS else (0.0, 1.0)
    if kind in SIGNED_KINDS:
        m = _nice_ceil(float(np.percentile(np.abs(v), 99)))
        return -m, m
    lo, hi = (float(x) for x in np.percentile(v, [1, 99]))
    if hi <= lo:
        pad = abs(lo) * 0.05 or 1.0
        lo, hi = lo - pad, hi + pad
    return lo, hi


def _nice_ceil(x: float) -> float:
    """The smallest of 1, 1.2, 1.5, 2, 2.5, 3, 4, 5, 6, 8 × 10^k that is ≥ x (1.0 for x ≤ 0)."""
    if not np.isfinite(x) or x <= 0:
        return 1.0
    k = np.floor(np.log10(x))
    for step_ in (1.0, 1.2, 1.5, 2.0, 2.5, 3.0, 4.0, 5.0, 6.0, 8.0, 10.0):
        if step_ * 10.0**k >= x * (1 - 1e-9):
            return float(step_ * 10.0**k)
    return float(10.0 ** (k + 1))


#: Line colours of the layers in :func:`~nemo.render.timeseries.frames_figure` (no green or red:
#: those mean QC pass/fail).
LAYER_COLOURS = ("tab:blue", "tab:orange", "tab:purple", "tab:brown", "tab:pink", "tab:olive",
                 "tab:cyan", "tab:gray")
#: Line colours of the surfaces (dark, so they read apart from the layers).
SURFACE_COLOURS = ("black", "dimgray", "darkslateblue", "saddlebrown")
#: Line markers of the layers (cycled with :data:`LAYER_COLOURS`).
LAYER_MARKERS = ("o", "s", "D", "^", "v", "P", "*", "h")

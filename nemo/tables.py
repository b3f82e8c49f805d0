"""Parquet tables: every arrow of the data flow is one of these files.

Per-vertex tables are keyed by an integer ``vertex`` column (the row index of the vertex in
the mesh the table was computed on). Each file stores, in its Parquet key/value metadata under
``nemo``, a JSON object with the unit, the command and parameters that made it, and for
per-vertex tables the mesh it was computed on (``mesh`` path, ``n_vertices``), so a table can
be traced back to its inputs and is never paired with another mesh. Writes are atomic (temporary file + rename).

The documented schemas live in :data:`SCHEMAS`; :func:`read_table` checks a file against one.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

from nemo import __version__
from nemo.atomic import atomic_path
from nemo.errors import NemoError

#: Required columns of each table kind (more columns may follow).
SCHEMAS: dict[str, tuple[str, ...]] = {
    "layer": ("vertex", "intensity"),
    "curvature": ("vertex", "H", "K"),
    "thickness": ("vertex", "thickness"),
    "directors": ("vertex", "x", "y", "z", "nx", "ny", "nz", "coherency"),
    "order": ("vertex", "S", "nx", "ny", "nz"),
    "align": ("vertex", "c"),
    "defects": ("x", "y", "z", "vertex", "S", "charge", "charge_winding",
                "charge_curvature", "charge_rounded"),
}


def write_table(df: pd.DataFrame, path: str | os.PathLike, **provenance) -> None:
    """Write ``df`` to Parquet atomically, with NEMO provenance metadata.

    Parameters
    ----------
    df : DataFrame
    path : path-like
        Output ``.parquet`` file; its folder is created if needed.
    **provenance
        JSON-serialisable key/values stored under the ``nemo`` metadata key (unit, command,
        parameters, input files).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    attrs, df.attrs = df.attrs, {}  # in-memory extras (a defects table's candidates: 96 KB for 254 objects) are
    try:  # not written: pandas would store them beside the provenance, and copy them at every slice on reading
        table = pa.Table.from_pandas(df, preserve_index=False)
    finally:
        df.attrs = attrs
    meta = dict(table.schema.metadata or {})
    meta[b"nemo"] = json.dumps({"version": __version__, **provenance}, default=_json_default).encode()
    table = table.replace_schema_metadata(meta)
    with atomic_path(path) as tmp:
        pq.write_table(table, tmp)


def _json_default(obj):
    if isinstance(obj, np.generic):  # numpy integers, floats and bools
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, os.PathLike):
        return str(obj)
    raise TypeError(f"not JSON serialisable: {type(obj)}")


def read_table(
    path: str | os.PathLike,
    kind: str | None = None,
    columns: tuple[str, ...] | None = None,
    n_vertices: int | None = None,
) -> pd.DataFrame:
    """Read a NEMO Parquet table and check it has the columns of ``kind``.

    Parameters
    ----------
    path : path-like
    kind : str, optional
        One of :data:`SCHEMAS`; the file must have its columns.
    columns : tuple of str, optional
        Further columns the caller needs.
    n_vertices : int, optional
        Vertex count of the mesh the caller pairs the table with. The table must have been
        computed on a mesh of that size (its provenance ``n_vertices``, when recorded) and
        may not refer to vertices beyond it.

    Raises
    ------
    NemoError
        Missing or non-Parquet file, a file that lacks required columns, or a table made on
        another mesh.
    """
    if kind is not None and kind not in SCHEMAS:
        raise ValueError(f"unknown table kind {kind!r}: one of {', '.join(SCHEMAS)}")
    path = Path(path)
    if not path.exists():
        raise NemoError(f"table not found: {path}")
    try:
        df = pq.read_table(path).to_pandas()
    except (pa.ArrowInvalid, OSError) as exc:
        raise NemoError(f"{path} is not a Parquet table ({exc})") from None
    missing_kind = [c for c in SCHEMAS.get(kind, ()) if c not in df.columns]
    missing_step = [c for c in columns or () if c not in df.columns and c not in missing_kind]
    if missing_kind or missing_step:
        what = " and ".join(w for w, m in ((f"a {kind} table", missing_kind), ("this step", missing_step)) if m)
        raise NemoError(
            f"{path} lacks column(s) {', '.join(missing_kind + missing_step)} needed for {what} "
            f"(it has: {', '.join(map(str, df.columns))}); was it made by the right nemo command?"
        )
    if n_vertices is not None:
        check_table_mesh(df, path, n_vertices)
    return df


def check_table_mesh(df: pd.DataFrame, path: str | os.PathLike, n_vertices: int) -> None:
    """Raise :class:`NemoError` unless a per-vertex table fits a mesh of ``n_vertices``.

    The table's provenance records the mesh it was computed on (``mesh``, ``n_vertices``); a
    different vertex count, or a ``vertex`` index beyond the mesh, means the table and the mesh
    do not belong together.
    """
    prov = read_provenance(path)
    made_on = prov.get("n_vertices")
    if made_on is not None and int(made_on) != int(n_vertices):
        raise NemoError(
            f"{path} was computed on another mesh ({prov.get('mesh', '?')}, {made_on} vertices) than "
            f"the one given ({n_vertices} vertices): pass the mesh the table was made on"
        )
    if "vertex" in df.columns and len(df):
        vmin, vmax = int(df["vertex"].min()), int(df["vertex"].max())
        bad = vmin if vmin < 0 else vmax
        if vmax >= n_vertices or vmin < 0:
            raise NemoError(
                f"{path} refers to vertex {bad} but the mesh has vertices 0 to {n_vertices - 1}: "
                "the table was computed on another mesh"
            )


def read_provenance(path: str | os.PathLike) -> dict:
    """The ``nemo`` metadata stored with a table (empty dict when absent)."""
    try:
        meta = pq.read_schema(path).metadata or {}
    except FileNotFoundError:
        raise NemoError(f"table not found: {path}") from None
    except (pa.ArrowInvalid, OSError) as exc:
        raise NemoError(f"{path} is not a Parquet table ({exc})") from None
    raw = meta.get(b"nemo")
    try:
        return json.loads(raw) if raw else {}
    except ValueError:
        return {}  # provenance written by hand or damaged: none rather than an error


def field_on_vertices(
    df: pd.DataFrame, column: str, n_vertices: int, path: str = "table", exact: bool = False
) -> np.ndarray:
    """Scatter a per-vertex column onto an (N,) array (NaN where the table has no row).

    Parameters
    ----------
    exact : bool
        The table must have exactly one row per vertex of the mesh (layers, curvature,
        thickness): a table from a smaller or larger mesh is refused.

    Raises
    ------
    NemoError
        If the table refers to vertices the mesh does not have (table made on another mesh).
    """
    if column not in df.columns:
        raise NemoError(f"{path} has no column {column!r} (columns: {', '.join(df.columns)})")
    vertex = df["vertex"].to_numpy()
    if exact and (len(vertex) != n_vertices or not np.array_equal(np.sort(vertex), np.arange(n_vertices))):
        raise NemoError(
            f"{path} has {len(vertex)} rows but the mesh has {n_vertices} vertices: "
            "the table was computed on another mesh; pass the mesh it was made on"
        )
    if len(vertex) and (vertex.min() < 0 or vertex.max() >= n_vertices):
        raise NemoError(
            f"{path} refers to vertex {int(vertex.max())} but the mesh has {n_vertices} vertices: "
            "the table was computed on another mesh"
        )
    out = np.full(n_vertices, np.nan)
    out[vertex] = df[column].to_numpy(dtype=np.float64)
    return out

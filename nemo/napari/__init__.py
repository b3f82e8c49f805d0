"""napari plugin and viewer for NEMO results (extra ``nemo-nematics[napari]``).

napari itself is imported only inside functions of this package, so
``nemo.napari.layers.layer_data`` and the sample writer work without it.

* :func:`nemo.napari.layers.add_nemo_layers` -- add a results folder's layers to a viewer;
* :func:`nemo.napari.layers.open_viewer` -- a new viewer with the layers and the field selector
  (``nemo view``);
* ``napari.yaml`` -- the npe2 manifest: a reader for NEMO results folders, the sample data
  "NEMO demo results" and "Synthetic vesicle", and the "Field selector" widget.
"""

from __future__ import annotations

from nemo.napari.layers import add_nemo_layers, layer_data, open_viewer, set_surface_field, to_napari

__all__ = ["add_nemo_layers", "layer_data", "open_viewer", "set_surface_field", "to_napari"]

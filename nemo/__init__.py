"""NEMO: depth-resolved nematic order and morphology of curved, multi-layered surfaces.

The library is a set of plain functions on numpy arrays and trimesh meshes:

* :mod:`nemo.io` -- lazy hyperstack reading (one (t, c) stack at a time) and writing;
* :mod:`nemo.mesh` -- the surface container, PLY/OBJ input/output;
* :mod:`nemo.surface` -- surface reconstruction from a volume;
* :mod:`nemo.synthetic` -- the paper's synthetic nematic vesicle;
* :mod:`nemo.morphology` -- curvature, thickness, area, volume;
* :mod:`nemo.peel`, :mod:`nemo.geometry`, :mod:`nemo.directors`, :mod:`nemo.order` --
  layers, tangent frames, directors, tangential Q-tensor average, inter-layer alignment;
* :mod:`nemo.defects` -- defect localisation and curvature-corrected charge;
* :mod:`nemo.tables` -- the Parquet tables that connect the steps.

The ``nemo`` command wraps them (``nemo --help``).
"""

__version__ = "0.1.0"

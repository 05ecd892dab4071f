"""The marching-cubes and marching-tetrahedra tables as stored in ``_lut_data.npz`` beside this.

They are derived by :mod:`recon_cli.stages.mcubes._luts` (which documents each table and its
conventions) and stored, so a command reads ~30 kB instead of deriving them (~0.4 s);
``tests/test_mcubes.py`` derives them again and checks that the stored file is identical.
"""

from __future__ import annotations

import os

import numpy as np

with np.load(os.path.join(os.path.dirname(os.path.abspath(__file__)), "_lut_data.npz")) as _z:
    MC_START = _z["MC_START"]
    MC_TRIS = _z["MC_TRIS"]
    MC_AMBIGUOUS = _z["MC_AMBIGUOUS"]
    MC_CENTRE = _z["MC_CENTRE"]
    MC_EDGES = _z["MC_EDGES"]
    MC_EDGE_KEY = _z["MC_EDGE_KEY"]
    FACE_CORNERS = _z["FACE_CORNERS"]
    MT_START = _z["MT_START"]
    MT_TRIS = _z["MT_TRIS"]
    MT_EDGES = _z["MT_EDGES"]
    MT_EDGE_KEY = _z["MT_EDGE_KEY"]
    CENTER = int(_z["CENTER"])

"""Reference geometries for the kinematics and statics tests (m, world / platform frame).

FRAME is the default 4.0 x 3.0 x 3.0 m frame; BOX the uncrossed 0.4 x 0.3 x 0.2 m platform
(rank-deficient with this frame: a_i and b_i have proportional x, y); CROSSED the crossed
platform of config/default.yaml (upper pairs crossed in x, lower pairs in y).
"""

from __future__ import annotations

import numpy as np

_CORNERS = np.array([[1, 1], [-1, 1], [-1, -1], [1, -1]] * 2, dtype=float)
FRAME = np.column_stack([_CORNERS * [2.0, 1.5], np.repeat([3.0, 0.0], 4)])
BOX = np.column_stack([_CORNERS * [0.2, 0.15], np.repeat([0.1, -0.1], 4)])
CROSSED = BOX[[1, 0, 3, 2, 7, 6, 5, 4]]
HOME = np.array([0.0, 0.0, 1.5, 0.0, 0.0, 0.0])

"""The compiled kernel of :func:`rtabmap_ros2.core.graph.rigid_products` (numba), in a module of its own
so that importing the graph does not import numba."""

from __future__ import annotations

import numpy as np

from rtabmap_ros2.core.compiled import jit


@jit()
def rigid_products_into(L, A, B, left, out):  # pragma: no cover - compiled
    """``out[n] = L[n] @ inv(A[n]) @ B[n]`` of rigid transforms (``inv(A[n]) @ B[n]`` unless ``left``)."""
    P = np.empty((3, 4))  # inv(A) @ B's top rows: [R_a' R_b | R_a' (t_b - t_a)]
    for n in range(A.shape[0]):
        for i in range(3):
            d = 0.0
            for k in range(3):
                d += A[n, k, i] * (B[n, k, 3] - A[n, k, 3])
            P[i, 3] = d
            for j in range(3):
                d = 0.0
                for k in range(3):
                    d += A[n, k, i] * B[n, k, j]
                P[i, j] = d
        for i in range(3):
            for j in range(4):
                if left:
                    d = L[n, i, 3] if j == 3 else 0.0
                    for k in range(3):
                        d += L[n, i, k] * P[k, j]
                    out[n, i, j] = d
                else:
                    out[n, i, j] = P[i, j]
        out[n, 3, 0] = 0.0
        out[n, 3, 1] = 0.0
        out[n, 3, 2] = 0.0
        out[n, 3, 3] = 1.0

"""Pure functions on triangle-mesh topology."""

from __future__ import annotations

from collections import defaultdict

import numpy as np


def boundary_loops(triangles: np.ndarray) -> list[np.ndarray]:
    """Closed boundary loops of a manifold triangle mesh.

    Args:
        triangles: ``(F, 3)`` vertex indices.

    Returns:
        One ``(n,)`` int64 array per loop, vertices in the direction the boundary edges have in their
        triangles. A mesh whose mouth and eyes are closed has exactly one loop (the face outline).
    """
    count: dict[tuple[int, int], int] = defaultdict(int)
    directed = []
    for a, b, c in triangles.tolist():
        for u, v in ((a, b), (b, c), (c, a)):
            count[(min(u, v), max(u, v))] += 1
            directed.append((u, v))
    nxt = {u: v for u, v in directed if count[(min(u, v), max(u, v))] == 1}
    loops, seen = [], set()
    for start in nxt:
        if start in seen:
            continue
        loop, v = [], start
        while v not in seen:
            seen.add(v)
            loop.append(v)
            v = nxt[v]
        loops.append(np.asarray(loop, dtype=np.int64))
    return loops

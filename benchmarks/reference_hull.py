"""The reference palette step for bench_decompose.py --reference: the progressive hull
simplification of Tan, Lien and Gingold (2017) as published with Tan, Echevarria and
Gingold (2018) (github.com/CraGL/fastLayerDecomposition, Convexhull_simplification.py, whose
``__main__`` loop this repeats, down to K vertices), timed in this fresh process.

    REFERENCE_PYTHON benchmarks/reference_hull.py CHECKOUT IMAGE.png K SCRATCH.obj

CHECKOUT is a clone of that repository; REFERENCE_PYTHON an interpreter with its
requirements (numpy < 2, scipy, cvxopt with GLPK, Pillow). Nothing is downloaded.
Prints ``palette S s, vertices N``.
"""

import sys
import time

checkout, path, k, scratch = sys.argv[1], sys.argv[2], int(sys.argv[3]), sys.argv[4]
sys.path.insert(0, checkout)

import numpy as np  # noqa: E402
from Convexhull_simplification import (  # noqa: E402
    remove_one_edge_by_finding_smallest_adding_volume_with_test_conditions,
    write_convexhull_into_obj_file,
)
from PIL import Image  # noqa: E402
from scipy.spatial import ConvexHull  # noqa: E402
from trimesh import TriMesh  # noqa: E402  (the checkout's own trimesh.py)

start = time.perf_counter()
hull = ConvexHull(np.asarray(Image.open(path).convert("RGB"), float).reshape(-1, 3) / 255.0)
write_convexhull_into_obj_file(hull, scratch)
while len(hull.vertices) > k:
    mesh = TriMesh.FromOBJ_FileName(scratch)
    before = len(mesh.vs)
    mesh = remove_one_edge_by_finding_smallest_adding_volume_with_test_conditions(mesh, option=2)
    hull = ConvexHull(mesh.vs)
    write_convexhull_into_obj_file(hull, scratch)
    if len(mesh.vs) == before:
        break
print(f"palette {time.perf_counter() - start:.3f} s, vertices {len(hull.vertices)}")

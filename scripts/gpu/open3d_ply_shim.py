"""A stand-in ``open3d`` for the lent GPU machine, installed by run.sh only when open3d is absent.

open3d's wheel (~400 MB) is too large to carry, and nerfstudio's training path uses it for one
thing: ``o3d.io.read_point_cloud`` of the dataset's ``ply_file_path`` (the synthetic scenes'
``sparse_pc.ply``) to initialise splatfacto's Gaussians. This reads the same vertices and colours
with plyfile (carried in .whl). Nothing else of open3d exists here; ns-export is not run there.
"""

from types import SimpleNamespace

import numpy as np


def read_point_cloud(path):
    from plyfile import PlyData

    vertex = PlyData.read(str(path))["vertex"]
    points = np.stack([vertex["x"], vertex["y"], vertex["z"]], axis=-1).astype(np.float64)
    names = vertex.data.dtype.names
    if all(c in names for c in ("red", "green", "blue")):
        colours = np.stack([vertex["red"], vertex["green"], vertex["blue"]], axis=-1).astype(np.float64) / 255.0
    else:
        colours = np.zeros((0, 3))
    return SimpleNamespace(points=points, colors=colours)


io = SimpleNamespace(read_point_cloud=read_point_cloud)

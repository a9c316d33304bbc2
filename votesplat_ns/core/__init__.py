"""The method itself, in pure torch/numpy: no nerfstudio import anywhere in this folder.

Paper §3.2 (masks to 2D votes: mask_sources, vote_maps, vote_cache), §3.3 (the vote pass and its
losses: vote_render; the CPU rasteriser with gsplat's conventions: rasterize_torch) and §3.4
(foreground, clustering, instances, semantics), plus the camera record and PLY/file helpers they share.
"""

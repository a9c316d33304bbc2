"""nerfstudio glue: everything here may import nerfstudio (at module level or inside functions).

The ``votesplat`` method spec (method), the splatfacto model with vote offsets and the RVD loss
(model, §3.3), the vote datamanager (datamanager, §3.2), the viewer panel, ``ns-export
votesplat-instances`` (export, §3.4), the splatfacto rasteriser patch, compat fixes and PLY retrofit.
"""

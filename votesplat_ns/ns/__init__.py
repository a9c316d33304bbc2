"""nerfstudio glue: everything here may import nerfstudio (at module level or inside functions).

One role per module: the ``votesplat`` method spec (method); the model and its options (model,
§3.3); the vote datamanager (datamanager, §3.2), its input checks (data_checks) and the SAM
options it shares with ``votesplat masks`` (mask_settings, masks); the viewer panel
(viewer) with its renders (viewer_render) and selection state (viewer_state); ``ns-export
votesplat-instances`` (export) writing with instance_export (§3.4); every patch of upstream code
(patches); the rasteriser entry points (rasterizer), offline LPIPS (compat), run loading (run),
selection and queries (selection, query), evaluation (evaluate) and PLY retrofit (retrofit).
"""

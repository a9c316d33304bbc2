"""VoteSplat (Hough Voting Gaussian Splatting) for nerfstudio.

Importing the package makes nerfstudio 1.1.5 checkpoints loadable under torch >= 2.6.
"""

from votesplat_ns.ns.patches import register_checkpoint_safe_globals

register_checkpoint_safe_globals()

__version__ = "0.1.0"

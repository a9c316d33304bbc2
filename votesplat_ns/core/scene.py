"""The one record of a trained VoteSplat scene (pure numpy/torch, no nerfstudio).

Export, evaluation, query/click and the PLY retrofit all read a run as a :class:`TrainedScene`:
splatfacto's raw Gaussian parameters plus the vote parameters of §3.3, as numpy arrays on the
CPU. :meth:`TrainedScene.gaussians` gives the activated tensors a rasteriser takes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Callable, Mapping, NamedTuple, Optional, Sequence, Tuple, Union

import numpy as np
import torch

from votesplat_ns.core.ply_io import SH_C0, GaussianRows, gaussian_vertex_table

VOTE_OFFSETS_KEY = "vote_offsets"
VOTE_SUPPORT_KEY = "vote_support"


def to_numpy(value: Any) -> np.ndarray:
    """A tensor (detached, float32, on the CPU) or array-like as a numpy array."""
    if hasattr(value, "detach"):
        value = value.detach().float().cpu().numpy()
    return np.asarray(value)


class Gaussians(NamedTuple):
    """Activated Gaussians as a rasteriser takes them, on one device, with their votes when asked for.

    :meth:`TrainedScene.gaussians` makes them from the record (only the finite ones, see
    ``TrainedScene.finite``); the viewer makes them from the live model each frame, as splatfacto's
    eval render sees it (``sh_degree`` None: ``colors`` are RGB [M, 3], splatfacto's degree-0 colours).
    """

    means: torch.Tensor  # [M, 3]
    quats: torch.Tensor  # [M, 4]
    scales: torch.Tensor  # [M, 3], exp of the log-scales
    opacities: torch.Tensor  # [M], sigmoid of the logits
    colors: torch.Tensor  # [M, K, 3] SH coefficients of degree sqrt(K) - 1 (or RGB [M, 3], see sh_degree)
    sh_degree: Optional[int]
    vote_offsets: Optional[torch.Tensor] = None  # [M, L, 3] Δp_i (§3.3); None: not asked for, or no votes
    vote_support: Optional[torch.Tensor] = None  # [M, L]; None with offsets: every Gaussian counts as supervised

    @property
    def num_gaussians(self) -> int:
        return int(self.means.shape[0])

    def to(self, device: Union[str, torch.device]) -> "Gaussians":
        return self._map(lambda tensor: tensor.to(device))

    def subset(self, keep: Optional[torch.Tensor]) -> "Gaussians":
        """The Gaussians in ``keep`` ([M] bool or indices; None: all of them)."""
        return self if keep is None else self._map(lambda tensor: tensor[keep])

    def _map(self, change: Callable[[torch.Tensor], torch.Tensor]) -> "Gaussians":
        return self._replace(
            means=change(self.means),
            quats=change(self.quats),
            scales=change(self.scales),
            opacities=change(self.opacities),
            colors=change(self.colors),
            vote_offsets=None if self.vote_offsets is None else change(self.vote_offsets),
            vote_support=None if self.vote_support is None else change(self.vote_support),
        )


@dataclass
class TrainedScene:
    """A trained run's Gaussians and votes, as splatfacto stores them (log-scales, opacity logits).

    With ``sh_degree`` 0, splatfacto keeps RGB logits in features_dc; they are stored here as SH
    DC exactly as nerfstudio's exporter converts them (RGB2SH(sigmoid(.))) and ``sh_rest`` is None.
    """

    means: np.ndarray  # [N, 3]
    log_scales: np.ndarray  # [N, 3]
    quats: np.ndarray  # [N, 4], not normalised
    opacity_logits: np.ndarray  # [N]
    sh_dc: np.ndarray  # [N, 3] float32 SH DC coefficients
    sh_rest: Optional[np.ndarray]  # [N, K - 1, 3] higher SH bands, None for degree 0
    vote_offsets: np.ndarray  # [N, L, 3] Δp_i per vote level (§3.3)
    vote_support: np.ndarray  # [N, L] vote supervision received; 0 = background at that level
    level_names: Tuple[str, ...]  # L names (config.vote_levels)
    sh_degree: int
    device: str = "cpu"  # where the model's tensors lived; rendering defaults to it

    @property
    def num_gaussians(self) -> int:
        return int(self.means.shape[0])

    # ------------------------------------------------------------------ constructors
    @classmethod
    def from_model(
        cls, model: Any, level_names: Optional[Sequence[str]] = None, sh_degree: Optional[int] = None
    ) -> "TrainedScene":
        """From a VoteSplat model: ``gauss_params``, ``config.vote_levels`` and ``config.sh_degree``."""
        config = getattr(model, "config", None)
        if level_names is None:
            level_names = getattr(config, "vote_levels", None)
        if sh_degree is None:
            sh_degree = getattr(config, "sh_degree", None)
        params = model.gauss_params
        scene = cls.from_params(params, level_names, sh_degree)
        tensors = [v for v in params.values() if hasattr(v, "device")]
        if tensors:
            scene.device = str(tensors[0].device)
        return scene

    @classmethod
    def from_params(
        cls, params: Mapping[str, Any], level_names: Optional[Sequence[str]] = None, sh_degree: Optional[int] = None
    ) -> "TrainedScene":
        """From splatfacto's raw gauss_params (tensors or arrays) plus ``vote_offsets`` and ``vote_support``."""
        keys = set(params.keys())
        missing_votes = [k for k in (VOTE_OFFSETS_KEY, VOTE_SUPPORT_KEY) if k not in keys]
        if missing_votes:
            raise ValueError(
                f"the checkpoint has no {' / '.join(missing_votes)}: it was not trained with the votesplat method; "
                "export instances from a VoteSplat run (ns-train votesplat ...)"
            )
        missing = [k for k in ("means", "scales", "quats", "opacities", "features_dc") if k not in keys]
        if missing:
            raise ValueError(f"Gaussian parameters are missing {missing}; pass splatfacto's gauss_params")
        offsets = to_numpy(params[VOTE_OFFSETS_KEY])
        support = to_numpy(params[VOTE_SUPPORT_KEY])
        if offsets.ndim == 2:  # a single level may be stored as [N, 3]
            offsets = offsets[:, None, :]
        if support.ndim == 1:
            support = support[:, None]
        if level_names is None:
            level_names = tuple(f"level_{i}" for i in range(offsets.shape[1]))
        level_names = tuple(str(name) for name in level_names)
        if len(level_names) != offsets.shape[1]:
            raise ValueError(
                f"the model has {offsets.shape[1]} vote levels but {len(level_names)} level names {level_names}"
            )
        rest = to_numpy(params["features_rest"]) if "features_rest" in keys else None
        if sh_degree is None:
            sh_degree = int(round(math.sqrt(rest.shape[1] + 1))) - 1 if rest is not None and rest.ndim == 3 else 0
        dc = to_numpy(params["features_dc"]).reshape(offsets.shape[0], 3)
        if sh_degree == 0:
            # float32 torch ops in nerfstudio's order, so the PLY bytes equal ns-export's
            dc = ((torch.sigmoid(torch.as_tensor(dc, dtype=torch.float32)) - 0.5) / SH_C0).numpy()
            rest = None
        rest = rest if rest is not None and rest.size else None
        return cls(
            means=to_numpy(params["means"]),
            log_scales=to_numpy(params["scales"]),
            quats=to_numpy(params["quats"]),
            opacity_logits=to_numpy(params["opacities"]).reshape(-1),
            sh_dc=dc.astype(np.float32),
            sh_rest=rest,
            vote_offsets=offsets,
            vote_support=support,
            level_names=level_names,
            sh_degree=int(round(math.sqrt(rest.shape[1] + 1))) - 1 if rest is not None else 0,
        )

    # ------------------------------------------------------------------ views of the record
    def finite(self, colours: bool = False) -> np.ndarray:
        """[N] bool: mean, scale, rotation and opacity (and with ``colours`` the SH) are finite.

        Rasterisers refuse non-finite input; such Gaussians are invisible anyway.
        """
        ok = np.isfinite(self.means).all(1) & np.isfinite(self.log_scales).all(1) & np.isfinite(self.quats).all(1)
        ok &= np.isfinite(self.opacity_logits)
        if colours:
            ok &= np.isfinite(self.sh_dc).all(1)
            if self.sh_rest is not None:
                ok &= np.isfinite(self.sh_rest).reshape(self.num_gaussians, -1).all(1)
        return ok

    def gaussians(
        self, keep: Optional[np.ndarray] = None, device: Union[str, torch.device, None] = None, votes: bool = False
    ) -> Gaussians:
        """Activated float32 tensors of the Gaussians in ``keep`` ([N] bool, default all) on ``device``, their votes with ``votes``."""
        device = torch.device(device if device is not None else self.device)
        select = (lambda a: a) if keep is None else (lambda a: a[keep])  # noqa: E731
        tensor = lambda a: torch.as_tensor(np.ascontiguousarray(select(a)), dtype=torch.float32, device=device)  # noqa: E731
        dc = tensor(self.sh_dc)[:, None, :]
        colors = torch.cat([dc, tensor(self.sh_rest)], dim=1) if self.sh_rest is not None else dc
        return Gaussians(
            means=tensor(self.means),
            quats=tensor(self.quats),
            scales=torch.exp(tensor(self.log_scales)),
            opacities=torch.sigmoid(tensor(self.opacity_logits)),
            colors=colors,
            sh_degree=int(round(math.sqrt(colors.shape[1]))) - 1,
            vote_offsets=tensor(self.vote_offsets) if votes else None,
            vote_support=tensor(self.vote_support) if votes else None,
        )

    def vertex_table(self) -> np.ndarray:
        """The standard 3DGS PLY vertex table of every Gaussian (see ``ply_io.gaussian_vertex_table``)."""
        return gaussian_vertex_table(
            self.means, self.sh_dc, self.sh_rest, self.opacity_logits, self.log_scales, self.quats
        )

    def vertex_rows(self) -> GaussianRows:
        """The rows of :meth:`vertex_table`, made only for the rows asked for (``ply_io.write_gaussian_table``
        writes an instance or the whole scene from them chunk by chunk, without the whole table)."""
        return GaussianRows(self.means, self.sh_dc, self.sh_rest, self.opacity_logits, self.log_scales, self.quats)

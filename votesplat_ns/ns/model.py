"""VoteSplat model: splatfacto + per-Gaussian vote offsets + the RVD loss (paper Eq. 13).

Thin nerfstudio glue. The maths lives in :mod:`votesplat_ns.core.vote_render` (vote pass and
losses); this module only
- adds ``gauss_params["vote_offsets"]`` [N, L, 3] and ``gauss_params["vote_support"]`` [N, L]
  so splatfacto's densify/prune strategy carries them,
- runs splatfacto's own ``get_outputs`` (on CPU through our torch rasteriser), and
- samples pixels that carry a 2D vote and adds the weighted vote and distortion losses as one loss
  ``"vote"`` (its two terms go to the metrics as ``vote_l1`` and ``vote_distortion``), reusing the
  projection and tile lists of the RGB pass (no second projection).

Its options, :class:`VoteSplatModelConfig` (each field a ``--pipeline.model.*`` flag of ``ns-train
votesplat``), live beside it, as splatfacto's do.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Literal, Optional, Tuple, Type, Union

import torch
from nerfstudio.cameras.cameras import Cameras
from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackLocation
from nerfstudio.models.splatfacto import SplatfactoModel, SplatfactoModelConfig, get_viewmat
from nerfstudio.utils.rich_utils import CONSOLE
from torch.nn import Parameter

from votesplat_ns.core.foreground import DEFAULT_MIN_MASKED_SHARE, foreground_from_exposure, mask_exposure
from votesplat_ns.core.vote_fused import KernelWarmUp, start_warm_up, use_fused, vote_losses_sampled
from votesplat_ns.core.vote_maps import pixels_and_targets
from votesplat_ns.core.vote_render import DIVERGED_VOTES, VoteRender, VoteRenderOptions, render_votes_tiled, vote_losses
from votesplat_ns.errors import VoteSplatInputError
from votesplat_ns.ns.compat import UnavailableMetric
from votesplat_ns.ns.patches import (
    cuda_calls_stay_on_cpu,
    install_rasterizer_in_splatfacto,
    install_untraced_viewmat,
    metrics_at_first_use,
)
from votesplat_ns.ns.rasterizer import project_for_votes, rasterize
from votesplat_ns.ns.retrofit_source import retrofit_gaussians
from votesplat_ns.ns.run import SPLAT_PARAM_NAMES
from votesplat_ns.ns.viewer import VoteSplatViewerState
from votesplat_ns.ns.vote_init import start_offsets_lifted

VOTE_PARAM_NAMES = ("vote_offsets", "vote_support")
# The fused vote losses do not read the host, so they cannot raise on diverged votes each step; the
# model reads their finiteness on every this-many-th fused vote step instead (a NaN loss otherwise trains on
# silently). Counted in vote steps, not trainer steps: a step count would miss every vote step of a schedule
# whose steps never meet it (votes every 4th step from step 500 never fall on a step ending in 99).
FUSED_FINITE_CHECK_EVERY = 100


def _raise_if_diverged(vote_loss: torch.Tensor) -> None:
    if not bool(torch.isfinite(vote_loss).all()):
        raise ValueError(DIVERGED_VOTES)


@dataclass
class VoteSplatModelConfig(SplatfactoModelConfig):
    """splatfacto plus VoteSplat's vote offsets and RVD loss."""

    _target: Type = field(default_factory=lambda: VoteSplatModel)
    vote_levels: Optional[Tuple[str, ...]] = None
    """Names of the mask levels, one 3D offset per Gaussian per level. Default: the datamanager's levels."""
    vote_loss_weight: float = 1.0
    """lambda_vote: weight of the L1 vote loss (in pixels)."""
    distortion_loss_weight: float = 0.05
    """lambda_d: weight of the vote depth distortion (with l1_pixels: its mean pairwise gap in pixels)."""
    vote_start_step: int = 500
    """Step at which the vote losses start (geometry settles first)."""
    vote_pixels_per_step: int = 4096
    """Pixels with a 2D vote sampled per vote step, shared by all levels (the loss is a mean, so a sample suffices)."""
    vote_every_n_steps: int = 4
    """Run the vote pass every n-th step (1: every step, as the paper, about splatfacto's run time; README.md)."""
    vote_transmittance: float = 0.01
    """Voting transmittance threshold: a Gaussian votes while the transmittance in front of it stays above this."""
    vote_weighting: Literal["uniform", "alpha_t"] = "uniform"
    """Ablation: 'alpha_t' blends votes with alpha*T weights instead of the paper's uniform mean."""
    vote_blend_space: Literal["3d", "2d"] = "3d"
    """Ablation: '2d' projects each Gaussian's vote first, then blends (the paper blends in 3D)."""
    vote_distortion: Literal["l1", "l1_pixels", "squared", "none"] = "l1_pixels"
    """Depth distortion of the votes: l1_pixels (scale-free, chosen on the tuning scenes), the paper's pair sum l1, squared, none."""
    votes_move_geometry: bool = False
    """Let the vote losses move the Gaussians' means/opacities/shapes (off: geometry is the RGB loss's job)."""
    vote_backend: Literal["auto", "torch", "triton"] = "auto"
    """Vote pass: auto (on CUDA the fused Triton losses where the switches allow, else torch code), torch, or triton."""
    retrofit_from: Optional[Path] = None
    """Add instances to a trained scene (a splatfacto run folder, a step-*.ckpt or a 3DGS .ply): train only the vote offsets."""
    retrofit_frame: Literal["auto", "dataparser", "dataset", "colmap"] = "auto"
    """Frame of a --pipeline.model.retrofit-from .ply: dataparser, dataset, colmap, or auto (README: retrofit frames)."""
    retrofit_init: Literal["zero", "lifted"] = "zero"
    """Start of a retrofit's offsets: zero, or lifted (each Gaussian's mask centroids lifted to 3D at its depth, mean over the training views)."""
    foreground_min_masked_share: Optional[float] = DEFAULT_MIN_MASKED_SHARE
    """After training, a Gaussian stays foreground at a level only if more than this share of its weight is in masks (None: all)."""
    clip_model_name: str = "ViT-B-16"
    """open_clip model name used by the viewer's text query box."""
    clip_checkpoint: Optional[Path] = None
    """open_clip weights file for the viewer's text query box (never downloaded); unset disables the box."""

    def vote_render_options(self) -> VoteRenderOptions:
        return VoteRenderOptions(
            weighting=self.vote_weighting,
            blend_space=self.vote_blend_space,
            distortion=self.vote_distortion,
            vote_transmittance=self.vote_transmittance,
            detach_geometry=not self.votes_move_geometry,
            backend=self.vote_backend,
        )


@dataclass
class VoteStepState:
    """What the parts of a training step's vote work hand on to one another. Plain attributes: an assignment to
    a torch Module's own attribute goes through Module.__setattr__'s checks, microseconds each on every step."""

    # (batch, its vote losses): computed in get_metrics_dict, used by get_loss_dict of the same batch
    early_losses: Tuple[Optional[Dict], Dict[str, torch.Tensor]] = field(default_factory=lambda: (None, {}))
    # [N, L] int32, the step that last counted each support entry (the fused backward counts the support)
    support_stamps: Optional[torch.Tensor] = None
    support_counted: bool = False  # by this step's fused backward: record_vote_support has nothing to add
    fused_steps: int = 0  # run by this model object (the finiteness check's clock)


def vote_step_due(step: int, start: int, every: int) -> bool:
    """Whether the vote losses run at ``step``: from ``start`` on, every ``every``-th step."""
    if every < 1:
        raise ValueError(f"vote_every_n_steps must be >= 1, got {every}")
    return step >= start and (step - start) % every == 0


class VoteSplatModel(SplatfactoModel):
    config: VoteSplatModelConfig

    def populate_modules(self):
        if self.config.vote_loss_weight < 0 or self.config.distortion_loss_weight < 0:
            raise ValueError(
                "vote_loss_weight and distortion_loss_weight must be >= 0 "
                f"(got {self.config.vote_loss_weight}, {self.config.distortion_loss_weight})"
            )
        if self.config.vote_every_n_steps < 1:
            raise ValueError(f"vote_every_n_steps must be >= 1 (got {self.config.vote_every_n_steps})")
        self.config.vote_levels = self._resolve_vote_levels()
        install_rasterizer_in_splatfacto()
        install_untraced_viewmat()
        self.vote_options = self.config.vote_render_options()
        self._kernel_warm_up: Optional[KernelWarmUp] = None  # compiling the fused kernels (CUDA)
        if (self.kwargs.get("metadata") or {}).get("vote_training"):
            # first, so that the compiling processes run beside the rest of the set-up: the Gaussians built or
            # read (a retrofit's PLY read and its frame rendered), the optimizers, the first step's forward
            self._start_kernel_warm_up(torch.device(self.kwargs.get("device") or "cpu"))
        # built on the CPU (splatfacto hard-codes one .cuda()); the pipeline moves the model to its device
        with metrics_at_first_use(), cuda_calls_stay_on_cpu(model_on_cpu=True):
            super().populate_modules()
        self.retrofitted = False
        self.retrofit_source_frame: Optional[str] = None  # the frame a retrofit PLY was read in
        if self.config.retrofit_from is not None:
            self._load_retrofit_source(Path(self.config.retrofit_from))
        num_points = self.gauss_params["means"].shape[0]
        num_levels = len(self.config.vote_levels)
        device = self.gauss_params["means"].device
        self.gauss_params["vote_offsets"] = Parameter(torch.zeros(num_points, num_levels, 3, device=device))
        # Not optimised (its optimizer never sees a gradient); it lives in gauss_params only so
        # that densification copies a parent's support to its children and pruning drops it.
        self.gauss_params["vote_support"] = Parameter(torch.zeros(num_points, num_levels, device=device))
        self.vote_step = VoteStepState()
        # made at the first draw, on the device the pipeline has moved the model to by then
        self._vote_pixel_generator: Optional[torch.Generator] = None
        self.viewer_state = VoteSplatViewerState(self)

    @property
    def vote_only(self) -> bool:
        """Train only the offsets on a frozen scene (retrofit)."""
        return self.config.retrofit_from is not None

    def _load_retrofit_source(self, source: Path) -> None:
        loaded = retrofit_gaussians(
            source,
            self.config.sh_degree,
            self.config.retrofit_frame,
            self.kwargs,
            tuple(self.gauss_params["features_rest"].shape[1:]),
        )
        if loaded is None:
            return
        gaussians, self.retrofit_source_frame = loaded
        for name in SPLAT_PARAM_NAMES:
            self.gauss_params[name] = Parameter(gaussians[name].to(self.gauss_params[name].device), requires_grad=False)
        self.retrofitted = True

    def get_training_callbacks(self, training_callback_attributes):
        if self.vote_only and not self.retrofitted:
            raise VoteSplatInputError(
                f"--pipeline.model.retrofit-from {self.config.retrofit_from} does not exist: "
                "give the trained splatfacto run folder or its step-*.ckpt"
            )
        if training_callback_attributes.optimizers is not None:
            # the trainer asks for callbacks right after loading a checkpoint (ns-train --load-dir)
            self.adopt_optimizers(training_callback_attributes.optimizers)
        self.continue_support_counts()
        callbacks = super().get_training_callbacks(training_callback_attributes)
        trainer, pipeline = training_callback_attributes.trainer, training_callback_attributes.pipeline
        datamanager = getattr(pipeline, "datamanager", None)
        if (
            self.vote_only
            and self.config.retrofit_init == "lifted"
            and trainer is not None
            and trainer._start_step == 0  # a resumed retrofit (--load-dir) keeps its trained offsets
            and hasattr(datamanager, "vote_maps_for_train_view")
        ):
            start_offsets_lifted(self, datamanager, log=CONSOLE.log)
        share = self.config.foreground_min_masked_share
        if share is not None and trainer is not None and hasattr(datamanager, "vote_batch"):
            # after the last step's other callbacks (densification) and before the final checkpoint is saved
            last_step = trainer._start_step + trainer.config.max_num_iterations - 1
            callbacks.append(
                TrainingCallback(
                    [TrainingCallbackLocation.AFTER_TRAIN_ITERATION],
                    lambda step: self.restrict_support_to_masked_gaussians(datamanager, share),
                    iters=(last_step,),
                )
            )
        return callbacks

    # ---------------------------------------------------------- resuming (ns-train --load-dir)
    # Patch of nerfstudio 1.1.5 (upstream issue #3554), all of it here: load_state_dict and adopt_optimizers.
    # Trainer.setup builds the optimizers from the model's Parameters, then _load_checkpoint runs
    # pipeline.load_pipeline (SplatfactoModel.load_state_dict replaces every gauss_params entry by a new
    # Parameter of the checkpoint's N), then optimizers.load_optimizers (which files the checkpoint's Adam
    # moments under the optimizers' old Parameters). Left alone, a resumed run steps orphaned tensors the
    # model never renders (it does not train), and densification rebuilds the Gaussians from those orphans
    # (IndexError once the checkpoint's N differs from the initial one). load_state_dict restores what the
    # reload undoes; adopt_optimizers, called from get_training_callbacks (the trainer's next call after
    # loading), points the optimizers at the model's own Parameters and moves the loaded state onto them.

    def load_state_dict(self, state_dict, **kwargs):  # type: ignore[override]
        super().load_state_dict(state_dict, **kwargs)
        # densification statistics of the Gaussians before the load mean nothing now: start them afresh
        # (gsplat sizes them to the loaded N at the next step), as after each densification step
        self.strategy_state = self.strategy.initialize_state(scene_scale=1.0)
        if self.vote_only:
            # the reload made fresh trainable Parameters: the scene stays frozen, and the checkpoint
            # holds the retrofitted Gaussians even if the retrofit source has gone since
            for name in SPLAT_PARAM_NAMES:
                self.gauss_params[name].requires_grad_(False)
            self.retrofitted = True

    def adopt_optimizers(self, optimizers) -> None:
        """Point nerfstudio's optimizers at the model's current Parameters, keeping their loaded state.

        A no-op when they already hold them (a fresh run). Optimizer state (Adam moments and step) moves
        to the new Parameter when its shape fits; otherwise that Parameter starts with fresh state.
        """
        for name, params in self.get_param_groups().items():
            optimizer = optimizers.optimizers.get(name)
            if optimizer is None:
                continue
            held = [param for group in optimizer.param_groups for param in group["params"]]
            if len(held) != len(params):
                raise RuntimeError(f"optimizer {name!r} holds {len(held)} tensors, the model has {len(params)}")
            replacement = {id(old): new for old, new in zip(held, params)}
            for group in optimizer.param_groups:
                for index, old in enumerate(group["params"]):
                    new = replacement[id(old)]
                    if new is old:
                        continue
                    state = optimizer.state.pop(old, None)
                    fits = state is not None and all(
                        value.shape == new.shape
                        for value in state.values()
                        if torch.is_tensor(value) and value.dim() > 0
                    )
                    if fits:
                        optimizer.state[new] = state
                    group["params"][index] = new
            optimizers.parameters[name] = list(params)

    @torch.no_grad()
    def continue_support_counts(self) -> None:
        """Undo the end-of-training sign of vote_support so that a resumed run keeps counting.

        restrict_support_to_masked_gaussians marks background as negative counts when a run ends;
        counting on from a negative value would mix the two. The end of the resumed run decides
        foreground again from the full count.
        """
        self.gauss_params["vote_support"].abs_()

    @torch.no_grad()
    def restrict_support_to_masked_gaussians(self, datamanager, min_masked_share: float) -> torch.Tensor:
        """Negate the vote support of Gaussians whose weight in the training views lies mostly outside the masks
        (no more than ``min_masked_share`` of it inside them).

        Returns the [N, L] foreground mask. See ``votesplat_ns.core.foreground``.
        """
        cameras = datamanager.train_dataset.cameras.to(self.device)

        def views():
            for index in range(cameras.shape[0]):
                camera = cameras[index : index + 1]
                labels = datamanager.vote_batch(index, int(camera.height.item()), int(camera.width.item()))[
                    "vote_labels"
                ]
                yield get_viewmat(camera.camera_to_worlds)[0], camera.get_intrinsics_matrices()[0], labels

        exposure = mask_exposure(
            rasterize,
            self.means,
            self.quats,
            torch.exp(self.scales),
            torch.sigmoid(self.opacities).squeeze(-1),
            views(),
            rasterize_mode=self.config.rasterize_mode,
        )
        foreground = foreground_from_exposure(exposure, min_masked_share)
        # > 0: foreground; 0: never supervised (zero offset); < 0: supervised, but seen mostly outside the
        # masks, so background. Every consumer tests > 0; the count itself is kept.
        support = self.gauss_params["vote_support"]
        support.copy_(torch.where(foreground, support.abs(), -support.abs()))
        return foreground

    def _resolve_vote_levels(self) -> Tuple[str, ...]:
        data_levels = (self.kwargs.get("metadata") or {}).get("vote_levels")
        levels = self.config.vote_levels or data_levels
        if not levels:
            raise ValueError(
                "no vote levels: set --pipeline.model.vote-levels (e.g. instance part) or use the votesplat datamanager"
            )
        if data_levels is not None and tuple(levels) != tuple(data_levels):
            raise ValueError(
                f"--pipeline.model.vote-levels {' '.join(levels)} does not match the datamanager's mask levels "
                f"{' '.join(data_levels)}; drop the flag to use the datamanager's levels"
            )
        return tuple(levels)

    @property
    def num_vote_levels(self) -> int:
        levels = self.config.vote_levels
        assert levels is not None, "populate_modules resolves the vote levels"
        return len(levels)

    def get_gaussian_param_groups(self) -> Dict[str, List[Parameter]]:
        groups = super().get_gaussian_param_groups()
        for name in VOTE_PARAM_NAMES:
            groups[name] = [self.gauss_params[name]]
        return groups

    def get_outputs(self, camera: Cameras) -> Dict[str, Union[torch.Tensor, List]]:
        if self.training and self.vote_only:
            return self._project_for_votes(camera)
        with cuda_calls_stay_on_cpu(model_on_cpu=self.device.type == "cpu"):
            outputs = super().get_outputs(camera)
        if not self.training:  # ns-viewer's overlay, votes picture and selection (no-op for other callers)
            tensors = {name: value for name, value in outputs.items() if isinstance(value, torch.Tensor)}
            outputs.update(self.viewer_state.extra_outputs(camera, tensors))
        return outputs

    def _project_for_votes(self, camera: Cameras) -> Dict[str, Union[torch.Tensor, List]]:
        """Vote-only training step: project the frozen Gaussians, no colour pass."""
        scale = self._get_downscale_factor()
        camera.rescale_output_resolution(1 / scale)
        K = camera.get_intrinsics_matrices()[0].to(self.device)
        width, height = torch.cat([camera.width.view(-1), camera.height.view(-1)]).tolist()  # one host read
        camera.rescale_output_resolution(scale)
        viewmat = get_viewmat(camera.camera_to_worlds.to(self.device))[0]
        self.info = project_for_votes(
            self.means,
            self.quats,
            torch.exp(self.scales),
            torch.sigmoid(self.opacities).squeeze(-1),
            viewmat,
            K,
            width,
            height,
        )
        return {}

    def get_metrics_dict(self, outputs, batch) -> Dict[str, torch.Tensor]:
        # The vote losses are computed here, where the batch first reaches the model, and handed to
        # get_loss_dict: splatfacto's metrics and colour losses read the GPU (PSNR, image copies),
        # so host work done before them overlaps the colour pass still running on the GPU. (On a stream of
        # their own, joined in get_loss_dict, a vote step cost 0.5-0.7 ms more host time: BENCHMARKS.md.)
        losses, terms = self._vote_losses(batch)
        self.vote_step.early_losses = (batch, losses)
        if self.training and self.vote_only:
            metrics = {"gaussian_count": self.num_points}
        else:
            metrics = super().get_metrics_dict(outputs, batch)
        metrics.update(terms)
        return metrics

    def get_image_metrics_and_images(self, outputs, batch):
        metrics, images = super().get_image_metrics_and_images(outputs, batch)
        if isinstance(getattr(self.lpips, "built", self.lpips), UnavailableMetric):
            metrics.pop("lpips", None)
        return metrics, images

    # ----------------------------------------------------------------- vote losses
    def votes_active(self) -> bool:
        if not self.training:
            return False
        if self.vote_only:  # a retrofit step is a vote step and nothing else
            return True
        return vote_step_due(self.step, self.config.vote_start_step, self.config.vote_every_n_steps)

    def get_loss_dict(self, outputs, batch, metrics_dict=None) -> Dict[str, torch.Tensor]:
        if self.training and self.vote_only:
            loss_dict: Dict[str, torch.Tensor] = {}
        else:
            loss_dict = super().get_loss_dict(outputs, batch, metrics_dict)
        early_batch, early_losses = self.vote_step.early_losses
        self.vote_step.early_losses = (None, {})
        loss_dict.update(early_losses if early_batch is batch else self._vote_losses(batch)[0])
        return loss_dict

    def _vote_losses(self, batch: Dict[str, torch.Tensor]) -> Tuple[Dict[str, torch.Tensor], Dict[str, torch.Tensor]]:
        """This step's vote loss ({"vote"}: the weighted vote L1 and distortion, one entry so that the trainer's
        sum of the losses costs one addition for the votes) and its terms for the metrics ({"vote_l1",
        "vote_distortion"}, without a gradient); ({}, {}) on steps that do not vote."""
        if not (self.votes_active() and "vote_labels" in batch):
            return {}, {}
        loss, terms = self.vote_loss_terms(batch, accumulate_grad=self._vote_grad_at_once())
        metrics = {"vote_l1": terms[0]}
        if self.config.vote_distortion != "none":
            metrics["vote_distortion"] = terms[1]
        return {"vote": loss}, metrics

    def _vote_grad_at_once(self) -> bool:
        """Whether the trainer's step takes the fused vote losses' gradient at once (``vote_losses_sampled``'s
        ``accumulate_grad``): not in a retrofit, whose loss dict holds only the vote loss (the trainer's backward
        needs a graph), not when the votes move the means (their gradient joins the colour losses'), not under
        mixed precision (the trainer's grad scaler scales the graph's gradients only), not without grad mode."""
        device_type = self.gauss_params["vote_offsets"].device.type
        if self.vote_only or self.config.votes_move_geometry or torch.is_autocast_enabled(device_type):
            return False
        return torch.is_grad_enabled()

    def vote_loss_terms(
        self, batch: Dict[str, torch.Tensor], accumulate_grad: bool = False
    ) -> Tuple[torch.Tensor, torch.Tensor]:
        """(loss, terms) on pixels sampled from the vote maps: loss = vote_loss_weight * vote L1 +
        distortion_loss_weight * distortion, each summed over levels; terms [2]: these two weighted terms,
        without a gradient. ``accumulate_grad``: on the fused path, the loss's gradient is added to the offsets'
        ``.grad`` here and the loss carries none (the torch path returns its graph either way)."""
        offsets = self.gauss_params["vote_offsets"]
        labels, centroids, voting = self._vote_maps(batch, offsets.device)
        # splatfacto renders at 1/d of the image resolution early in training; positions in the
        # continuous pixel frame (pixel centre = index + 0.5) scale by exactly 1/d.
        scale = 1.0 / self._get_downscale_factor()
        flat_labels = labels.reshape(labels.shape[0], -1)
        # One pixel sample and one walk for all levels: membership depends only on geometry. Uniform
        # among the pixels that carry a vote.
        size = (self.config.vote_pixels_per_step,)
        weights = (self.config.vote_loss_weight, self.config.distortion_loss_weight)
        if self.config.vote_distortion == "none":
            weights = (weights[0], 0.0)
        if not voting.numel():
            # a view without any vote: the loss is 0, still connected to the offsets
            return offsets.sum() * 0.0, offsets.new_zeros(2)
        sample = torch.randint(voting.numel(), size, device=offsets.device, generator=self._vote_generator())
        if use_fused(self.vote_options, offsets, voting):
            if self._kernel_warm_up is not None:
                self._kernel_warm_up.join()  # the kernels it compiled are then in Triton's cache
                self._kernel_warm_up = None
            # The Triton backend with the default switches: the pixel lookup, render and losses in three
            # launches, no host read (so no value checks: a diverged vote gives a NaN loss, not an error).
            info = self.info
            means = self.gauss_params["means"]
            losses = vote_losses_sampled(
                info["means2d"][0],
                info["conics"][0],
                info["opacities"][0],
                means if self.config.votes_move_geometry else means.detach(),
                offsets,
                info["viewmats"][0],
                info["Ks"][0],
                sample,
                voting,
                flat_labels,
                centroids,
                labels.shape[-1],
                scale,
                info["isect_offsets"][0],
                info["flatten_ids"],
                info["tile_size"],
                self.vote_options,
                weights,
                self._support_in_backward(),
                check_inputs=False,  # built the same way every step (the checks were a fair part of its host time)
                accumulate_grad=accumulate_grad,
            )
            self.vote_step.fused_steps += 1
            if self.vote_step.fused_steps % FUSED_FINITE_CHECK_EVERY == 0:
                # one host read every FUSED_FINITE_CHECK_EVERY vote steps, so diverged votes still stop training
                _raise_if_diverged(losses["vote"])
            return losses["total"], losses["terms"]
        pixel_xy, target_xy, valid = pixels_and_targets(voting[sample], labels.shape[-1], flat_labels, centroids, scale)
        # Targets are finite wherever valid (valid is their finiteness) and render_votes_tiled checks the
        # votes, so vote_losses' own input checks (a host read every step) would never fire.
        render = self.render_votes(pixel_xy, self._votes())
        losses = vote_losses(render, target_xy, valid, self.vote_options, check_inputs=False)
        vote = weights[0] * losses["vote"].sum()
        distortion = weights[1] * losses["distortion"].sum()
        return vote + distortion, torch.stack([vote, distortion]).detach()

    def _support_in_backward(self) -> Tuple[torch.Tensor, torch.Tensor, int]:
        """What the fused backward needs to count this step's vote support (``vote_losses_sampled``'s
        ``support``): the counts, the stamps (made again when densification changed N) and the step."""
        counts = self.gauss_params["vote_support"].detach()
        state = self.vote_step
        if state.support_stamps is None or state.support_stamps.shape != counts.shape:
            state.support_stamps = torch.full(counts.shape, -1, dtype=torch.int32, device=counts.device)
        state.support_counted = True
        return counts, state.support_stamps, int(self.step)

    def _vote_generator(self) -> torch.Generator:
        """The vote pixels' own random stream, seeded with ns-train's seed (--machine.seed). Drawing them from
        torch's default stream would shift splatfacto's draws (random backgrounds, densification's split
        samples): a run that votes would train other colours than one that does not."""
        if self._vote_pixel_generator is None:
            self._vote_pixel_generator = torch.Generator(device=self.device)
            self._vote_pixel_generator.manual_seed(torch.initial_seed())
        return self._vote_pixel_generator

    def _start_kernel_warm_up(self, device: torch.device) -> None:
        """On CUDA, compiles the fused vote kernels in the background while training sets up and starts (the
        first vote step would otherwise wait for the compiler); that step joins the processes. Started once, as
        the model is built for ns-train (a model built otherwise compiles at its first vote step)."""
        if device.type != "cuda":
            return
        probe = torch.zeros(1, self.num_vote_levels, 3, device=device)
        if use_fused(self.vote_options, probe, probe):
            self._kernel_warm_up = start_warm_up(self.num_vote_levels, self.vote_options, probe.device)

    def _votes(self) -> torch.Tensor:
        """[N, L, 3] world-space votes p + dp (p without gradient unless votes_move_geometry)."""
        means = self.gauss_params["means"]
        if not self.config.votes_move_geometry:
            means = means.detach()
        return means[:, None, :] + self.gauss_params["vote_offsets"]

    def render_votes(self, pixel_xy: torch.Tensor, votes: Optional[torch.Tensor] = None) -> VoteRender:
        """The vote pass of every level at ``pixel_xy`` [P,2], on the projection of the last get_outputs call
        (``votes``: ``_votes()`` when the caller has them)."""
        info = self.info
        return render_votes_tiled(
            info["means2d"][0],
            info["conics"][0],
            info["opacities"][0],
            info["depths"][0],
            self._votes() if votes is None else votes,
            info["viewmats"][0],
            info["Ks"][0],
            pixel_xy,
            info["isect_offsets"][0],
            info["flatten_ids"],
            info["tile_size"],
            self.vote_options,
        )

    @torch.no_grad()
    def vote_pixel_error(self, camera: Cameras, batch: Dict[str, torch.Tensor]) -> torch.Tensor:
        """Mean L1 distance in pixels between rendered and 2D votes, per level, over every pixel with a vote.

        Rendered at the camera's full resolution; pixels whose voting set is empty are left out.
        Levels without any vote in this view give NaN.
        """
        labels, centroids, voting = self._vote_maps(batch, self.device)
        self.get_outputs(camera.to(self.device))
        flat_labels = labels.reshape(labels.shape[0], -1)
        pixel_xy, target_xy, valid = pixels_and_targets(voting, labels.shape[-1], flat_labels, centroids, 1.0)
        render = self.render_votes(pixel_xy)
        used = valid & (render.count > 0)[:, None]  # [P, L]
        error = (render.projected_vote - target_xy).abs().sum(-1)  # [P, L]
        errors = [error[used[:, level], level].mean() for level in range(labels.shape[0])]  # NaN when empty
        return torch.stack(errors)

    def _vote_maps(
        self, batch: Dict[str, torch.Tensor], device: torch.device
    ) -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        # int16/int32 [L, H, W] at the datamanager's image resolution; [L, K+1, 2] pixel-index coordinates; int32
        # [C] the pixels carrying a vote. No copy when the datamanager keeps them on the device (cache_vote_maps
        # gpu); non_blocking otherwise: it pins them on CUDA, so the copies do not wait for the GPU's queue.
        labels = batch["vote_labels"].to(device, non_blocking=True)
        centroids = batch["vote_centroids"].to(device, non_blocking=True)
        voting = batch["vote_pixels"].to(device, non_blocking=True)
        if labels.shape[0] != self.num_vote_levels:
            raise ValueError(
                f"the vote maps have {labels.shape[0]} levels but the model has vote_levels={self.config.vote_levels}; "
                "make --pipeline.model.vote-levels match the datamanager's mask levels"
            )
        return labels, centroids, voting

    @torch.no_grad()
    def record_vote_support(self) -> None:
        """Count, per Gaussian and level, the steps in which its offset received a vote gradient.

        A Gaussian gets a vote gradient when it is in the voting set M of a sampled pixel that
        carries a 2D vote, so support > 0 marks the foreground for clustering. The fused losses count
        in their backward (``vote_losses_sampled``'s ``support``) and count that membership itself: a
        member whose gradients from several pixels cancel to an exact 0 (L1 signs) counts there, not here.
        """
        if self.vote_step.support_counted:  # the fused backward has counted it
            self.vote_step.support_counted = False
            return
        grad = self.gauss_params["vote_offsets"].grad
        if grad is not None:
            self.gauss_params["vote_support"].add_(grad.ne(0).any(dim=-1))

    def step_post_backward(self, step):
        self.record_vote_support()
        if not self.vote_only:  # a retrofit keeps the trained scene as it is: no densify/prune
            super().step_post_backward(step)

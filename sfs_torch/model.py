"""The whole method as one ``nn.Module``: :class:`ShapeFromShading` around :func:`sfs_torch.estimate`.

The stages have their own thin modules beside their functions
(:class:`sfs_torch.reflectance_map.LightingEstimator`,
:class:`sfs_torch.texton.TextonFeatures`, :class:`sfs_torch.integrability.Integrator`,
...); this one stores a :class:`sfs_torch.pipeline.PipelineConfig` and runs
:func:`sfs_torch.pipeline.estimate` with it, so that the method composes with other
torch code (``nn.Sequential``-style wrappers, ``.to(device)``, ``repr``) without a second
implementation of the pipeline.
"""
from __future__ import annotations

from typing import Any, Dict, Optional, Sequence, Union

from omegaconf import DictConfig
from torch import Tensor, nn

from .pipeline import Estimate, PipelineConfig, estimate, resolve_config

__all__ = ["ShapeFromShading"]


class ShapeFromShading(nn.Module):
    """Normals, lighting, confidence (and depth) of a diffuse object from one image.

    ``forward`` is :func:`sfs_torch.pipeline.estimate` with this module's config: same
    inputs, same :class:`~sfs_torch.pipeline.Estimate`, computed on the device of
    ``image`` (a numpy image runs on the CPU).

    State: the module holds its options only, no tensors, parameters or buffers, so
    ``.to(device)`` / ``.cuda()`` return it unchanged and the device is chosen by the
    input. Nothing is kept between calls either: as in :func:`~sfs_torch.pipeline.estimate`,
    every call loads the example-geometry database (built and stored in the on-disk cache
    under ``SFS_TORCH_CACHE`` on first use, read from it afterwards), shades it for the
    call's lighting and trains a forest for it (or reads that forest from the on-disk forest
    cache, ``training.cache_forests``). The forest is deterministic given
    ``forest.seed``, so two calls on the same input give the same result.

    Args:
        config: a :class:`~sfs_torch.pipeline.PipelineConfig`, a (nested) dict or an
            omegaconf config of overrides, or ``None`` for the defaults; merged onto the
            defaults and validated here (:func:`sfs_torch.pipeline.resolve_config`), the
            result stored as :attr:`config`.
        progress: show progress bars while the database is built.

    Not differentiable: the forest's splits are hard thresholds.

    Raises:
        ValueError: a config that does not fit the pipeline's options (here), or bad
            inputs (in ``forward``, as :func:`~sfs_torch.pipeline.estimate` raises them).

    Example:
        >>> model = ShapeFromShading({"forest": {"n_trees": 4}}, progress=False)
        >>> model.config.forest.n_trees
        4
    """

    def __init__(
        self, config: Union[None, PipelineConfig, DictConfig, Dict[str, Any]] = None, *, progress: bool = True
    ):
        super().__init__()
        self.config: PipelineConfig = resolve_config(config)
        self.progress = bool(progress)

    def forward(
        self,
        image: Any,
        mask: Any,
        *,
        lighting: Optional[Tensor] = None,
        focal: Optional[float] = None,
        principal_point: Optional[Sequence[float]] = None,
        integrate: Optional[str] = None,
    ) -> Estimate:
        """Run :func:`~sfs_torch.pipeline.estimate` on one image (or a batch) with this module's config.

        Args:
            image: linear RGB in [0, 1], :math:`(B, 3, H, W)` or :math:`(3, H, W)` tensor, or
                an :math:`(H, W, 3)` numpy array.
            mask: object pixels, :math:`(B, 1, H, W)`, :math:`(1, H, W)` or :math:`(H, W)`,
                bool or {0, 1}.
            lighting: known SH lighting :math:`(3, 9)` / :math:`(B, 3, 9)` in the camera
                frame; skips the reflectance-map estimate.
            focal: focal length in pixels (perspective); default ``config.camera.focal``.
            principal_point: ``(cx, cy)`` in pixels; default ``config.camera.principal_point``.
            integrate: ``None``, ``"l2"``, ``"l1"`` or ``"conv"``; default
                ``config.integrate.method``.

        Returns:
            :class:`~sfs_torch.pipeline.Estimate` on the device of ``image``; tensors without
            the batch axis for unbatched input.
        """
        return estimate(
            image,
            mask,
            focal=focal,
            principal_point=principal_point,
            lighting=lighting,
            integrate=integrate,
            config=self.config,
            progress=self.progress,
        )

    def extra_repr(self) -> str:
        cfg = self.config
        return (
            f"database={cfg.database.collection!r}, forest=(n_trees={cfg.forest.n_trees}, "
            f"max_depth={cfg.forest.max_depth}), integrate={cfg.integrate.method!r}, focal={cfg.camera.focal}"
        )

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

from dataclasses import replace
from typing import Any, Dict, Optional, Sequence, Union

import torch
from omegaconf import DictConfig
from torch import Tensor, nn

from . import geometry_db
from .geometry_db import DatabaseConfig, GeometryDatabase
from .pipeline import Estimate, PipelineConfig, estimate, resolve_config

__all__ = ["ShapeFromShading"]


class ShapeFromShading(nn.Module):
    """Normals, lighting, confidence (and depth) of a diffuse object from one image.

    ``forward`` is :func:`sfs_torch.pipeline.estimate` with this module's config: same
    inputs, same :class:`~sfs_torch.pipeline.Estimate`, computed on the device of
    ``image`` (a numpy image runs on the CPU).

    State: the module holds its options and, from its first call on, the example-geometry
    database of ``config.database``: loaded once (built and stored in the on-disk cache
    under ``SFS_TORCH_CACHE`` on first use, read and verified from it afterwards), then kept
    on every device that an input came on, moved there once, and handed to
    :func:`~sfs_torch.pipeline.estimate` (``database=``) instead of reading the file on each
    call. :meth:`database` gives it; changing ``config.database`` drops it, and
    :meth:`clear_database` frees it. It is no parameter or buffer: ``state_dict()`` is
    empty, ``.to(device)`` / ``.cuda()`` return the module unchanged and the device is
    chosen by the input. Every call shades the database for the call's lighting and trains
    a forest for it (or reads that forest from the on-disk forest cache,
    ``training.cache_forests``). The forest is deterministic given ``forest.seed``, so
    two calls on the same input give the same result.

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
        # the database of _database_config, by device: the CPU one as loaded, the others moved from it
        self._databases: Dict[torch.device, GeometryDatabase] = {}
        self._database_config: Optional[DatabaseConfig] = None

    def database(self, device: Union[str, torch.device, None] = None) -> GeometryDatabase:
        """The example-geometry database of ``config.database`` on ``device`` (default CPU).

        Loaded by :func:`~sfs_torch.geometry_db.load_database` on the first request (and
        after ``config.database`` changed), moved to each device once; later requests
        return the same tensors.

        Raises:
            ValueError: ``device`` is no device, or a CUDA device where torch sees none
                (before anything is loaded).
        """
        try:
            device = torch.device("cpu" if device is None else device)
        except (RuntimeError, TypeError):
            raise ValueError(f"device must be a torch.device or a name such as 'cpu' or 'cuda:0', "
                             f"got {device!r}") from None
        if device.type == "cuda" and not torch.cuda.is_available():
            raise ValueError(f"device {str(device)!r}: torch {torch.__version__} sees no CUDA device here")
        if device.type == "cuda" and device.index is None:
            device = torch.device("cuda", torch.cuda.current_device())
        if self._database_config != self.config.database:
            self._databases.clear()
            self._database_config = replace(self.config.database)
        cpu = torch.device("cpu")
        if cpu not in self._databases:
            self._databases[cpu] = geometry_db.load_database(self._database_config, progress=self.progress)
        if device not in self._databases:
            self._databases[device] = self._databases[cpu].to(device)
        return self._databases[device]

    def clear_database(self) -> None:
        """Drop the held database (every device); the next call loads it again."""
        self._databases.clear()
        self._database_config = None

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
            integrate: ``"none"``, ``"l2"``, ``"l1"`` or ``"conv"``; ``None``:
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
            database=self.database(image.device if isinstance(image, Tensor) else None),
        )

    def extra_repr(self) -> str:
        cfg = self.config
        return (
            f"database={cfg.database.collection!r}, forest=(n_trees={cfg.forest.n_trees}, "
            f"max_depth={cfg.forest.max_depth}), integrate={cfg.integrate.method!r}, focal={cfg.camera.focal}"
        )

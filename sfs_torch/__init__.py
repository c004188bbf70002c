"""sfs-torch: discriminative shape from shading in uncalibrated illumination.

A PyTorch implementation of Richter & Roth, "A discriminative approach to perspective
shape from shading in uncalibrated illumination", Computers & Graphics 2015. The
modules follow the paper's pipeline (Fig. 2):

- :mod:`sfs_torch.denoise`: a noisy image denoised (added)
- :mod:`sfs_torch.silhouette`: silhouette features and coarse normals (Sec. 6.1)
- :mod:`sfs_torch.reflectance_map`: lighting from the silhouette (Sec. 7, 8)
- :mod:`sfs_torch.geometry_db`, :mod:`sfs_torch.shapes`, :mod:`sfs_torch.rendering`:
  the example-geometry training database (Sec. 4)
- :mod:`sfs_torch.texton`: colour and texton features (Sec. 6)
- :mod:`sfs_torch.forest`: the von Mises-Fisher regression forest (Sec. 5)
- :mod:`sfs_torch.camera`: perspective adaptation (Sec. 8)
- :mod:`sfs_torch.integrability`: integrability refinement and depth (Sec. 5, 9.2)
- :mod:`sfs_torch.lighting`, :mod:`sfs_torch.metrics`, :mod:`sfs_torch.io`: SH
  lighting, evaluation metrics, files
- :mod:`sfs_torch.pipeline`: :func:`estimate`, the whole method
- :mod:`sfs_torch.model`: :class:`ShapeFromShading`, the whole method as an ``nn.Module``
"""
from importlib import import_module

from ._openmp import short_openmp_waits

__version__ = "0.1.0"
__all__ = ["estimate", "Estimate", "PipelineConfig", "ShapeFromShading", "short_openmp_waits", "__version__"]


def __getattr__(name: str):
    # Lazy, so that importing the package (or its command-line entry points) neither
    # imports torch nor changes the process: ``sfs_torch.cli`` chooses OpenMP's wait
    # policy before torch starts (docs/forest.md), which an eager import would pre-empt.
    if name in ("estimate", "Estimate", "PipelineConfig"):
        return getattr(import_module(".pipeline", __name__), name)
    if name == "ShapeFromShading":
        return getattr(import_module(".model", __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")

"""What the command-line apps (``sfs-torch``, ``sfs-torch-eval``) share: where a job writes, and
refusing an unwritable ``out`` before Hydra opens its log file there."""
from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import torch
from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from omegaconf import DictConfig


def output_folder(cfg: DictConfig, program: str) -> Path:
    """``out``; in a sweep (``-m``) or without ``out``, the job's Hydra output folder.

    In a sweep every job gets its own subfolder (``hydra.sweep.dir/hydra.sweep.subdir``, the
    sweep folder being ``out`` when given), so that parallel jobs never write into one folder.
    """
    if HydraConfig.initialized():
        hydra_cfg = HydraConfig.get()
        if not cfg.out or hydra_cfg.mode == RunMode.MULTIRUN:
            return Path(hydra_cfg.runtime.output_dir)
    if not cfg.out:
        raise ValueError(f"out must be given when the config was not composed by the {program} command")
    return Path(cfg.out)


def exit_unless_writable(path: Path, message: str) -> None:
    """Create ``path`` and write a temporary file in it, or print ``message: <reason>`` on stderr and exit 2."""
    try:
        path.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=path):
            pass
    except OSError as err:
        print(f"{message}: {err.strerror or err}", file=sys.stderr)
        sys.exit(2)


def parse_device(name: str) -> torch.device:
    """The ``device=`` option as a torch device, or one ``ValueError`` saying what is wrong and what to do."""
    try:
        device = torch.device(name)
    except (RuntimeError, TypeError):
        raise ValueError(f"device must be 'cpu', 'cuda' or 'cuda:N', got {name!r}") from None
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(
            f"device={name} but torch {torch.__version__} sees no CUDA device here; run with device=cpu, or "
            "install a CUDA build of torch (README)"
        )
    return device

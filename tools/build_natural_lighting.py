"""Build ``sfs_torch/data/natural_lighting.npz`` from CC0 environment maps on PyPI.

The ``bpy==5.0.1`` wheel ships eight CC0 Poly Haven HDRIs (1K EXR, Greg Zaal) under
``bpy/5.0/datafiles/studiolights/world/``. This script downloads the wheel once
(``pip download --no-deps``; it is opened as a zip archive, never installed), reads the
maps (``pip install OpenEXR`` first), and writes:

- ``names``, ``maps``: each map area-averaged to 32 x 64 (equirectangular, row 0 looks
  up), linear RGB, for image formation with a full environment
  (:mod:`sfs_torch.natural_lighting`);
- ``sh``: each map's 9-term SH lighting (Lambertian-convolved, SPEC basis) in the frame
  of a camera looking at the horizon, normalised to unit RMS coefficient;
- ``prior_mean``, ``prior_cov``: mean and covariance of the lighting, normalised likewise
  (``sfs_torch.natural_lighting.normalise_lighting``), over random camera orientations
  (azimuth uniform, pitch uniform in +-30 deg, roll uniform in +-10 deg) and white-balance gains (log-normal, sigma 0.1).

None of R&H's probes is used: they stay evaluation lightings.

    pip install OpenEXR && python tools/build_natural_lighting.py
"""
from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import zipfile
from pathlib import Path

import numpy as np
import torch

from sfs_torch.lighting import rotate_sh
from sfs_torch.natural_lighting import environment_to_sh, normalise_lighting, random_camera_rotations

WHEEL = "bpy==5.0.1"
FOLDER = "bpy/5.0/datafiles/studiolights/world/"
OUT = Path(__file__).resolve().parents[1] / "sfs_torch" / "data" / "natural_lighting.npz"
MAP_SHAPE = (32, 64)
ROTATIONS_PER_MAP = 2000


def area_downsample(radiance: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    h, w = radiance.shape[:2]
    fy, fx = h // shape[0], w // shape[1]
    return radiance[: shape[0] * fy, : shape[1] * fx].reshape(shape[0], fy, shape[1], fx, 3).mean((1, 3))


def read_exr(data: bytes) -> np.ndarray:
    import OpenEXR  # development-only dependency of this script

    with tempfile.NamedTemporaryFile(suffix=".exr") as tmp:
        tmp.write(data)
        tmp.flush()
        with OpenEXR.File(tmp.name) as exr:
            return np.asarray(exr.channels()["RGB"].pixels, dtype=np.float32)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--wheel", type=Path, help="an already downloaded bpy wheel")
    parser.add_argument("--out", type=Path, default=OUT)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="sfs-torch-bpy-") as tmp:
        wheel = args.wheel
        if wheel is None:
            subprocess.run([sys.executable, "-m", "pip", "download", "--no-deps", "-d", tmp, WHEEL], check=True)
            wheel = next(Path(tmp).glob("*.whl"))
        with zipfile.ZipFile(wheel) as archive:
            names = sorted(n for n in archive.namelist() if n.startswith(FOLDER) and n.endswith(".exr"))
            radiances = [read_exr(archive.read(n)) for n in names]
            licence = archive.read(FOLDER + "license.txt").decode()
    generator = torch.Generator().manual_seed(args.seed)
    sh_maps, samples = [], []
    for radiance in radiances:
        sh = environment_to_sh(torch.from_numpy(radiance)[None].double())[0]
        sh = normalise_lighting(sh[None])[0]
        sh_maps.append(sh)
        rot = random_camera_rotations(ROTATIONS_PER_MAP, generator)
        rotated = rotate_sh(sh.expand(ROTATIONS_PER_MAP, 3, 9), rot)
        gains = (0.1 * torch.randn(ROTATIONS_PER_MAP, 3, 1, generator=generator, dtype=torch.float64)).exp()
        rotated = rotated * gains
        samples.append(normalise_lighting(rotated))
    samples_t = torch.cat(samples).flatten(1).numpy()
    mean = samples_t.mean(0)
    cov = np.cov(samples_t, rowvar=False)
    # the normalisation fixes the coefficients' norm: one null direction, kept invertible
    cov = cov + 1e-6 * np.trace(cov) / cov.shape[0] * np.eye(cov.shape[0])
    maps = np.stack([area_downsample(r, MAP_SHAPE) for r in radiances]).astype(np.float32)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(
        args.out,
        names=np.array([Path(n).stem for n in names]),
        maps=maps,
        sh=torch.stack(sh_maps).numpy().astype(np.float32),
        prior_mean=mean.reshape(3, 9).astype(np.float64),
        prior_cov=cov.astype(np.float64),
        licence=np.array(licence),
    )
    print(f"wrote {args.out}: {len(names)} maps ({', '.join(Path(n).stem for n in names)}), "
          f"{len(samples_t)} prior samples")


if __name__ == "__main__":
    main()

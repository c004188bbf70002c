"""Build ``sfs_torch/data/relief_prior.npz``: the learnt prior against the bas-relief ambiguity.

Renders the true normal maps of the default database's 100 training shapes (the same
split as the forest's database: ``sfs_torch.geometry_db.database_split``; the held-out
shapes are never seen) in 100 uniformly random views each, at 128 px, crops them
(``sfs_torch.relief_prior.relief_training_views``) and trains
``sfs_torch.relief_prior.ReliefNet`` on them (``fit_relief_net``'s defaults: 16 epochs,
1024 hidden units). No test image, lighting or estimate is read. About 30 minutes on one
thread of 2 CPU cores; the meshes are fetched first if missing (``sfs-torch-data``).

    python tools/build_relief_prior.py
"""
from __future__ import annotations

import argparse
import inspect
import time
from pathlib import Path

import torch
from tqdm import tqdm

from sfs_torch.geometry_db import DatabaseConfig, _mesh_root, database_split
from sfs_torch.relief_prior import fit_relief_net, relief_training_views, save_relief_net
from sfs_torch.shapes import load_shape

OUT = Path(__file__).resolve().parents[1] / "sfs_torch" / "data" / "relief_prior.npz"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--views", type=int, default=100, help="random views per training shape")
    parser.add_argument("--epochs", type=int, default=inspect.signature(fit_relief_net).parameters["epochs"].default)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=OUT)
    args = parser.parse_args()
    start = time.perf_counter()
    cfg = DatabaseConfig()
    names = database_split(cfg).train
    root = _mesh_root(cfg.collection, progress=True)
    meshes = [load_shape(name, root).mesh for name in names]
    views = relief_training_views(meshes, args.views, torch.Generator().manual_seed(args.seed + 1),
                                  resolution=cfg.resolution, scale=cfg.scale,
                                  progress=lambda it: tqdm(it, desc="views", unit="shape"))
    print(f"{len(views)} views of {len(meshes)} shapes in {time.perf_counter() - start:.0f} s")
    net = fit_relief_net(views, epochs=args.epochs, seed=args.seed,
                         progress=lambda it: tqdm(it, desc="training", unit="epoch"))
    save_relief_net(net, str(args.out), dict(shapes=len(meshes), views=len(views), epochs=args.epochs,
                                             seed=args.seed, collection=cfg.collection))
    print(f"wrote {args.out} in {time.perf_counter() - start:.0f} s")


if __name__ == "__main__":
    main()

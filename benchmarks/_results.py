"""What the accuracy benchmarks write: their arguments and results, as one JSON file; how
sure a change between two variants on the same images is, how far a ratio to the
silhouette prior could move with the shapes drawn, and each shape's own median; and the
lightings their ``--side`` options choose."""
from __future__ import annotations

import argparse
import json
from typing import Sequence

import numpy as np


def write_results(args: argparse.Namespace, **results) -> None:
    """Write ``{"args": <args as strings>, **results}`` to ``args.out`` (its folder made if
    missing) and say where."""
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"args": {k: str(v) for k, v in vars(args).items()}, **results}, indent=2))
    print(f"wrote {args.out}")


def side_lightings(parser: argparse.ArgumentParser, args: argparse.Namespace) -> list:
    """The ``args.lights`` lightings of ``args.side`` after its first ``args.first_light``
    (:func:`sfs_torch.datasets.scene_lightings` with ``args.light_seed`` and
    ``args.exposure``); options that do not fit end the script through ``parser.error``."""
    # imported here: openmp_waits.py imports this module before it sets OpenMP's variables
    from sfs_torch.datasets import scene_lightings

    if args.first_light < 0:
        parser.error(f"--first-light must be >= 0, got {args.first_light}")
    try:
        return scene_lightings(args.first_light + args.lights, args.side, seed=args.light_seed,
                               exposure=args.exposure)[args.first_light:]
    except ValueError as error:
        parser.error(f"--lights, --light-seed, --exposure: {error}")


def paired_bootstrap(first: Sequence[float], second: Sequence[float], *, draws: int = 5000, level: float = 0.9,
                     seed: int = 0) -> dict:
    """The change from ``first`` to ``second``, each one value per image for the same images
    in the same order: the change of the median and of the mean over the images, each with
    its ``level`` percentile interval over ``draws`` resamples of the images (with
    replacement, both variants resampled alike, so the interval is that of a paired change).

    Returns:
        ``{"median": change, "median_interval": [low, high], "mean": ..., "mean_interval": ...}``.
    """
    a, b = np.asarray(first, dtype=float), np.asarray(second, dtype=float)
    if a.shape != b.shape or a.ndim != 1 or len(a) == 0:
        raise ValueError(f"first and second must hold one value per image, alike, got {a.shape} and {b.shape}")
    picks = np.random.default_rng(seed).integers(0, len(a), size=(draws, len(a)))
    tails = [(1 - level) / 2 * 100, (1 + level) / 2 * 100]
    medians = np.median(b[picks], axis=1) - np.median(a[picks], axis=1)
    means = (b - a)[picks].mean(axis=1)
    return {"median": float(np.median(b) - np.median(a)), "median_interval": np.percentile(medians, tails).tolist(),
            "mean": float((b - a).mean()), "mean_interval": np.percentile(means, tails).tolist()}


def ratio_over_shapes(errors: Sequence[float], prior: Sequence[float], shapes: Sequence[str], *, draws: int = 5000,
                      level: float = 0.9, seed: int = 0) -> list:
    """The ``level`` percentile interval of ``median(errors) / median(prior)`` over ``draws``
    resamples of the shapes: each draw takes as many shapes as there are, with replacement,
    each with all of its images (one value per image in the three sequences, ``shapes``
    naming each image's shape). Its width is what the choice of a few test shapes alone can
    move the ratio by, apart from any change of the method.

    Returns:
        ``[low, high]``.
    """
    errors, prior = np.asarray(errors, dtype=float), np.asarray(prior, dtype=float)
    if not (errors.shape == prior.shape == (len(shapes),)) or len(shapes) == 0:
        raise ValueError(f"errors, prior and shapes must hold one value per image, alike, got {errors.shape}, "
                         f"{prior.shape} and {len(shapes)}")
    names, shape_index = np.unique(np.asarray(shapes), return_inverse=True)
    images = [np.flatnonzero(shape_index == i) for i in range(len(names))]
    ratios = []
    for picks in np.random.default_rng(seed).integers(0, len(names), size=(draws, len(names))):
        rows = np.concatenate([images[i] for i in picks])
        ratios.append(np.median(errors[rows]) / np.median(prior[rows]))
    return np.percentile(ratios, [(1 - level) / 2 * 100, (1 + level) / 2 * 100]).tolist()


def median_per_shape(values: Sequence[float], shapes: Sequence[str]) -> dict:
    """The median of ``values`` over each shape's images (one value per image, ``shapes``
    naming each image's shape), the shapes in the order they first come.

    Returns:
        ``{shape: median}``.
    """
    if len(values) != len(shapes) or len(shapes) == 0:
        raise ValueError(f"values and shapes must hold one entry per image, alike, got {len(values)} and {len(shapes)}")
    grouped = {}
    for value, shape in zip(values, shapes):
        grouped.setdefault(shape, []).append(float(value))
    return {shape: float(np.median(group)) for shape, group in grouped.items()}

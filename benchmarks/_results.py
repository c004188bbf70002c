"""What the accuracy benchmarks write: their arguments and results, as one JSON file."""
from __future__ import annotations

import argparse
import json


def write_results(args: argparse.Namespace, **results) -> None:
    """Write ``{"args": <args as strings>, **results}`` to ``args.out`` (its folder made if
    missing) and say where."""
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"args": {k: str(v) for k, v in vars(args).items()}, **results}, indent=2))
    print(f"wrote {args.out}")

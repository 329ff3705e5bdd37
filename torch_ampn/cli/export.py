"""``torch-ampn export CKPT OUT``: a model file (weights and arguments) from a Lightning checkpoint.

The file is what :meth:`torch_ampn.forming.AMPNSurrogate.load` reads without Lightning: an
application or a colleague rolls the surrogate out with :mod:`torch_ampn.rollout` and needs
neither the training code nor its checkpoint's optimizer state.
"""

from __future__ import annotations

import argparse
from pathlib import Path


def main(argv: list[str] | None = None) -> Path:
    """Write the model file; returns its path."""
    parser = argparse.ArgumentParser(prog="torch-ampn export", description=__doc__.split("\n")[0])
    parser.add_argument("checkpoint", help="a torch-ampn Lightning checkpoint (e.g. outputs/.../last.ckpt)")
    parser.add_argument("out", type=Path, help="the model file to write (e.g. model.pt)")
    args = parser.parse_args(argv)

    from torch_ampn.cli.train import _check_checkpoint

    _check_checkpoint("export", args.checkpoint)
    from torch_ampn.training import load_module

    module = load_module(args.checkpoint)
    surrogate = module.surrogate
    if not surrogate.statistics_frozen:
        raise ValueError(
            f"{args.checkpoint}: its normalisation statistics were never fitted (an untrained model)"
        )
    meta = {
        "checkpoint": str(args.checkpoint),
        "training_meshes": module._training_meshes,  # topology key -> nodes, for a mesh check
    }
    path = surrogate.save(args.out, meta)
    print(f"wrote {path} ({sum(p.numel() for p in surrogate.parameters()):,} parameters)")
    return path

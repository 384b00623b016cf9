"""Run the ``triplet`` command with :class:`TrainConfig` / :class:`MeshConfig` defaults overridden (bench only).

Why: a candidate default is measured end to end through the real command before it becomes a default, without
a command-line option for every field. ``TRIPLET_BENCH_CFG`` holds a JSON object of ``field: value`` pairs; a
``mesh.`` prefix names a :class:`~triplet_cl.mesh.refine.MeshConfig` field. Every configuration the command
builds starts from these defaults (its options still apply on top), and the run's ``config.json`` records them.

    TRIPLET_BENCH_CFG='{"prior_metallic": 0.01}' python bench/cfg_triplet.py train DATA --out RUN
"""

from __future__ import annotations

import dataclasses
import json
import os
import sys


def _patch(cls, over: dict) -> None:
    names = {f.name for f in dataclasses.fields(cls)}
    bad = sorted(set(over) - names)
    if bad:
        raise SystemExit(f"cfg_triplet.py: {cls.__name__} has no field(s) {', '.join(bad)}")
    init = cls.__init__

    def __init__(self, *args, **kwargs):
        init(self, *args, **{**over, **kwargs})

    cls.__init__ = __init__


def main() -> int:
    over = json.loads(os.environ.get("TRIPLET_BENCH_CFG", "{}"))
    from triplet_cl.mesh.refine import MeshConfig
    from triplet_cl.train import TrainConfig

    _patch(TrainConfig, {k: v for k, v in over.items() if not k.startswith("mesh.")})
    _patch(MeshConfig, {k[5:]: v for k, v in over.items() if k.startswith("mesh.")})
    from triplet_cl.cli.main import main as triplet

    sys.argv[0] = "triplet"
    return triplet()


if __name__ == "__main__":
    sys.exit(main())

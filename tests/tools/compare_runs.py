"""Bitwise comparison of training runs (a refactoring's "no behaviour change" check).

    python tests/tools/compare_runs.py RUN_A RUN_B [RUN_A2 RUN_B2 ...]

For each pair: every array of the latest checkpoint (parameters, density statistics, Adam moments)
compared bit for bit, ``metrics.json`` test PSNR / SSIM, and ``lights.json`` / ``triplets.ply``
byte for byte. Exit status 1 when anything differs. Typical use: train the same short run
(``triplet train --demo --iterations 200 --out A``) from the base commit (``git archive`` into a
folder on ``PYTHONPATH``) and from the branch, then compare A and B.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np


def compare(a: Path, b: Path) -> bool:
    ca = a / "checkpoints" / (a / "checkpoints" / "latest").read_text().strip()
    cb = b / "checkpoints" / (b / "checkpoints" / "latest").read_text().strip()
    with np.load(ca) as za, np.load(cb) as zb:
        keys = sorted((set(za.files) | set(zb.files)) - {"meta"})
        diff = [k for k in keys
                if k not in za.files or k not in zb.files or za[k].tobytes() != zb[k].tobytes()]
    ma, mb = (json.loads((r / "metrics.json").read_text()) for r in (a, b))
    same = {f: (a / f).read_bytes() == (b / f).read_bytes() for f in ("lights.json", "triplets.ply")}
    ok = not diff and ma["psnr"] == mb["psnr"] and ma["ssim"] == mb["ssim"] and all(same.values())
    print(f"{a} vs {b}: checkpoint {ca.name} {'identical' if not diff else 'DIFFERS in ' + ', '.join(diff)}; "
          f"PSNR {ma['psnr']:.6f} / {mb['psnr']:.6f}, SSIM {ma['ssim']:.6f} / {mb['ssim']:.6f}; "
          + ", ".join(f"{f} {'same' if s else 'DIFFERS'}" for f, s in same.items()))
    return ok


def main(argv: list[str]) -> int:
    if len(argv) < 2 or len(argv) % 2:
        print(__doc__.strip().splitlines()[2].strip(), file=sys.stderr)
        return 2
    paths = [Path(p) for p in argv]
    return 0 if all([compare(paths[i], paths[i + 1]) for i in range(0, len(paths), 2)]) else 1


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))

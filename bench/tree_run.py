"""Run the ``triplet`` command line, or a script of this tree, with ``triplet_cl`` imported from another
source tree (an older commit checked out with ``git worktree add --detach DIR COMMIT``): old and new
side by side under the same conditions.

Usage::

    python bench/tree_run.py TREE ARGS...                  # the CLI of TREE: triplet ARGS...
    python bench/tree_run.py TREE --script FILE ARGS...     # FILE (e.g. bench/step_profile.py) on TREE's package

Prints the wall time of the whole call last (``WALL ... s``). The import shim is
``bench/train_step.py``'s :func:`import_tree` (the package maps ``autodiff/``, ``cli/`` and
``kernels_cl/`` into ``triplet_cl.*``, so the tree is imported by hand, not from site-packages).
"""

from __future__ import annotations

import runpy
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from train_step import import_tree  # noqa: E402


def main() -> int:
    if len(sys.argv) < 3 or sys.argv[1] in ("-h", "--help"):
        print(__doc__)
        return 0 if len(sys.argv) > 1 and sys.argv[1] in ("-h", "--help") else 2
    tree = Path(sys.argv[1]).resolve()
    if not (tree / "triplet_cl" / "__init__.py").is_file():
        print(f"tree_run.py: error: {tree} is not a source tree of triplet_cl (no triplet_cl/__init__.py)",
              file=sys.stderr)
        return 2
    import_tree(tree)
    t0 = time.perf_counter()
    rc = 0
    if sys.argv[2] == "--script":
        if len(sys.argv) < 4 or not Path(sys.argv[3]).is_file():
            print("tree_run.py: error: --script needs an existing FILE", file=sys.stderr)
            return 2
        script = sys.argv[3]
        sys.argv = [script] + sys.argv[4:]
        runpy.run_path(script, run_name="__main__")
    else:
        from triplet_cl.cli.main import main as cli_main

        rc = cli_main(sys.argv[2:])
    print(f"WALL {time.perf_counter() - t0:.1f} s (triplet_cl from {tree})")
    return rc


if __name__ == "__main__":
    sys.exit(main())

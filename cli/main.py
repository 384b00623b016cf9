"""``triplet`` — the command line. Parses arguments and calls the library; no logic of its own."""

from __future__ import annotations

import argparse
import sys

from triplet_cl import __version__
from triplet_cl.errors import TripletError


def _gib(n: int) -> str:
    return f"{n / 2**30:.1f} GiB" if n >= 2**30 else f"{n / 2**20:.0f} MiB"


def cmd_devices(args: argparse.Namespace) -> int:
    """List every OpenCL platform/device and mark the one that would be chosen."""
    from triplet_cl.device import list_devices, resolve_spec

    infos = list_devices()
    chosen, _, _ = resolve_spec(args.device)
    header = f"{'':2}{'P:D':5} {'type':5} {'CUs':>4} {'global':>9} {'max alloc':>9} {'fp64':4}  {'OpenCL C':18} device"
    print(header)
    for info in infos:
        mark = "*" if info.index == chosen.index else " "
        print(
            f"{mark:2}{info.index:5} {info.type:5} {info.compute_units:4d} {_gib(info.global_mem_bytes):>9} "
            f"{_gib(info.max_alloc_bytes):>9} {'yes' if info.fp64 else 'no':4}  "
            f"{info.opencl_c_version[:18]:18} {info.platform_name} / {info.device_name}"
        )
    how = "--device" if args.device else ("$TRIPLET_DEVICE" if _env_spec() else "default: first GPU, else first CPU")
    print(f"\n* chosen: {chosen.index} {chosen.platform_name} / {chosen.device_name} ({how})")
    return 0


def _env_spec() -> str:
    import os

    return os.environ.get("TRIPLET_DEVICE", "").strip()


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="triplet",
        description="Mesh-based inverse rendering (Triplet) with OpenCL kernels and hand-derived adjoints.",
    )
    p.add_argument("--version", action="version", version=f"triplet_cl {__version__}")
    sub = p.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True

    d = sub.add_parser("devices", help="list OpenCL platforms/devices and the one that would be chosen")
    d.add_argument(
        "--device",
        default=None,
        help="device to mark as chosen: 'P:D' indices or a substring of the platform/device name "
        "(default: $TRIPLET_DEVICE, else the first GPU, else the first CPU)",
    )
    d.set_defaults(func=cmd_devices)
    return p


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except TripletError as exc:
        print(f"triplet {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())

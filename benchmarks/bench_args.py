"""Command-line options shared by the memory benchmarks (imported from the scripts' own folder)."""
from __future__ import annotations

import argparse


def add_blas_threads(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--blas-threads", type=int, default=0,
                    help="numpy's OpenBLAS threads (0: the library's default, as the recorded figures; "
                         "memory_node's blas_threads default is 1)")


def apply_blas_threads(args: argparse.Namespace) -> None:
    if args.blas_threads:
        from comper_msgs_py.blas import set_numpy_blas_threads
        print(f"[bench] numpy BLAS threads: {set_numpy_blas_threads(args.blas_threads)}", flush=True)

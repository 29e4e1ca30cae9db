"""Command-line options and process handling shared by the memory benchmarks (imported from the scripts' own folder)."""
from __future__ import annotations

import argparse
import os
import signal
import subprocess


def add_blas_threads(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--blas-threads", type=int, default=0,
                    help="numpy's OpenBLAS threads (0: the library's default, as the recorded figures; "
                         "memory_node's blas_threads default is 1)")


def apply_blas_threads(args: argparse.Namespace) -> None:
    if args.blas_threads:
        from comper_msgs_py.blas import set_numpy_blas_threads
        print(f"[bench] numpy BLAS threads: {set_numpy_blas_threads(args.blas_threads)}", flush=True)


def stop_node(proc: subprocess.Popen, timeout: float = 20.0) -> None:
    """SIGINT to a node started with start_new_session=True (its whole process group), SIGKILL after timeout."""
    if proc.poll() is None:
        os.killpg(proc.pid, signal.SIGINT)
        try:
            proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)

"""The gateway's node workers each do their linear algebra on one thread (gateway/blas_threads.py).

OpenBLAS starts its own threads when numpy loads unless told otherwise; the gateway command tells it
before anything imports numpy, and keeps an operator's own setting.
"""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from gateway.blas_threads import BLAS_THREAD_VARIABLES, one_blas_thread

# Runs `pipesentry gateway --check` in this process, then does some linear algebra and prints how many
# native threads the process has and what OpenBLAS was told.
AFTER_THE_COMMAND = """
import os, sys
from typer.main import get_command
from pipesentry.cli import app
get_command(app).main(["gateway", "--check", "--config", sys.argv[1]], standalone_mode=False)
import numpy as np
a = np.random.default_rng(0).random((300, 300))
np.linalg.pinv(a @ a)
print(len(os.listdir("/proc/self/task")), os.environ["OPENBLAS_NUM_THREADS"])
"""


def test_each_variable_an_operator_left_unset_is_set_to_one():
    environ = {"OMP_NUM_THREADS": "4", "MKL_NUM_THREADS": " ", "PATH": "/bin"}
    assert one_blas_thread(environ) == ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")
    assert environ == {"OMP_NUM_THREADS": "4", "MKL_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "PATH": "/bin"}
    assert one_blas_thread(environ) == ()  # set once, left alone after


def _run_the_command(tmp_path: Path, **environ: str) -> tuple[int, str]:
    config = tmp_path / "gateway.toml"
    config.write_text(f'[database]\nurl = "sqlite:///{tmp_path / "ps.db"}"\n[[nodes]]\nid = "a"\nurl = "/dev/ttyUSB0"\n')
    env = {k: v for k, v in os.environ.items() if k not in BLAS_THREAD_VARIABLES} | environ
    out = subprocess.run([sys.executable, "-c", AFTER_THE_COMMAND, str(config)], env=env, capture_output=True,
                         text=True, timeout=120, check=True).stdout.split()
    return int(out[-2]), out[-1]


@pytest.mark.skipif(not Path("/proc/self/task").is_dir(), reason="counts threads in /proc (Linux)")
def test_the_gateway_command_pins_blas_before_numpy_loads_and_keeps_an_operators_setting(tmp_path):
    threads, told = _run_the_command(tmp_path)
    assert (threads, told) == (1, "1")  # no OpenBLAS thread beside the main one
    if (os.cpu_count() or 1) >= 2:  # OpenBLAS starts no more threads than there are cores
        threads, told = _run_the_command(tmp_path, OPENBLAS_NUM_THREADS="2")
        assert told == "2" and threads > 1

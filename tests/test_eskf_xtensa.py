"""The error-state filter's C as ESP32 code (codegen.natmod.xtensa_eskf: Debian's LLVM 22 with the natmod's -Os,
mpy_ld, qemu-system-xtensa de233_fpu) on a simulated car drive: it starts, never repairs its covariance, and its
positions are bit for bit those of the cffi build of the same C (both round every float32 product: no fused
multiply-add on either side); the single steps run and count what the benchmark reports.
"""

from __future__ import annotations

import sys

import numpy as np
import pytest

from codegen.board.loader import load_board
from codegen.natmod import xtensa_eskf, xtensa_llvm
from conftest import ROOT, mpy_dir, require, require_tool
from test_kernel_natmod import native_tree

sys.path.insert(0, str(ROOT / "benchmarks"))
from device import _host_positions, eskf_steps  # noqa: E402


@pytest.fixture(scope="module")
def image(tmp_path_factory):
    for tool in xtensa_llvm.TOOLS:
        require_tool(tool)
    require(not xtensa_llvm.missing_tools(), f"the LLVM route needs {xtensa_llvm.missing_tools()}")
    require_tool("qemu-system-xtensa")
    folder = tmp_path_factory.mktemp("eskf-xtensa")
    return xtensa_eskf.build(native_tree(folder), mpy_dir(), folder / "build")


def test_the_esp32_code_follows_the_host_build_bit_for_bit(image):
    from codegen.kernel.eskf import EskfConfig

    steps, window_of = eskf_steps(load_board().board, "car", 0, 60.0)
    answers = xtensa_eskf.run(image, steps)
    assert answers[0].code == 0  # calibrated at rest
    started = [a.started for a in answers]
    assert any(started) and started[-1], "the filter did not start on the drive"
    assert answers[-1].repairs == 0
    device = np.array([a.position for a in answers])
    host = _host_positions(steps, EskfConfig().cov_dt_s, EskfConfig().nhc_dt_s)
    assert np.array_equal(device, host.astype(np.float32).astype(np.float64))
    assert np.max(np.abs(device[-1])) > 50.0  # it went somewhere: not a filter stuck at its start
    windows = [sum(a.instructions for a, w in zip(answers, window_of) if w == k) for k in range(max(window_of) + 1)]
    assert all(count > 100_000 for count in windows)  # counted (512 samples cannot take fewer)


def test_single_steps_run_on_the_state_and_leave_it_unchanged(image):
    steps, _ = eskf_steps(load_board().board, "car", 0, 40.0)
    alone = [("Q",), ("K",), ("N",), ("U",)]
    answers = xtensa_eskf.run(image, steps + alone + [steps[-1]])
    single = answers[len(steps):len(steps) + len(alone)]
    assert all(a.instructions > 100 for a in single)
    assert single[1].code == 1  # the covariance after the drive is usable
    assert single[3].code == 1  # and takes a scalar update
    # the step after them sees the state as before: the same window again from the same state
    again = xtensa_eskf.run(image, steps + [steps[-1]])
    assert np.array_equal(answers[-1].position, again[-1].position)
    assert np.array_equal(answers[-1].velocity, again[-1].velocity)

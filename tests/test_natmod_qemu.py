"""dr_native.mpy run on its own instruction set: MicroPython's QEMU port (built from the tree conftest.mpy_dir()
names, once, into the cache: codegen.natmod.qemu_arm) loads the natmod built for armv6m (MICROBIT, Cortex-M0: the
RP2040's instruction set) and armv7m (MPS2_AN385, Cortex-M3) and runs both algorithms on the recorded walk
(../shared/data/gnss-imu-walk): every window's output and state bit for bit equal to the cffi build of the same C,
and float32-close to the float64 reference.

Cost: the two firmware builds (about a minute each, once per MicroPython tree and compiler), then a few seconds per
test.
"""

from __future__ import annotations

import numpy as np
import pytest

from codegen.kernel import fused as F
from codegen.kernel import reference as ref
from codegen.natmod import qemu_arm, windows
from conftest import mpy_dir, require_shared_data, require_tool
from kernelkit import Case, run_reference
from test_kernel_natmod import make, native_tree

ARM = [("MICROBIT", "armv6m"), ("MPS2_AN385", "armv7m")]
SEED_WINDOWS = 4
FUSED_SECONDS = 24  # of the walk after the calibration, one window and one GPS fix per second
CALIBRATION_S = 10.0


@pytest.fixture(scope="module")
def walk():
    from codegen.board.loader import load_board
    from codegen.sim.run import build_run

    require_shared_data("gnss-imu-walk")
    board = load_board().board
    return board, build_run("replay-walk", board)


@pytest.fixture(scope="module")
def natmods(tmp_path_factory):
    """arch -> dr_native.mpy of the default board's generated tree."""
    require_tool("make")
    require_tool("arm-none-eabi-gcc")
    built = {}
    for _, arch in ARM:
        native = native_tree(tmp_path_factory.mktemp(arch))
        done = make(native, arch)
        assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-3000:]
        built[arch] = (native / "dr_native.mpy").read_bytes()
    return built


def firmware(board: str):
    require_tool("qemu-system-arm")
    require_tool("arm-none-eabi-gcc")
    return qemu_arm.firmware(mpy_dir(), board)


def seed_steps(board, run):
    t = run.t_us * 1e-6
    dt = np.diff(run.t_us).astype(np.int32)
    k = int(np.searchsorted(t, CALIBRATION_S))
    n = board.algorithm.window
    return [("C", run.counts[:k])] + [("P", run.counts[k + j * n:k + (j + 1) * n], dt[k + j * n:k + (j + 1) * n])
                                      for j in range(SEED_WINDOWS)]


def fused_steps(run):
    t = run.t_us * 1e-6
    dt = np.diff(run.t_us).astype(np.int32)
    vel = run.gps.device_velocity()
    k = int(np.searchsorted(t, CALIBRATION_S))
    steps = [("C", run.counts[:k])]
    for second in range(int(CALIBRATION_S) + 1, int(CALIBRATION_S) + 1 + FUSED_SECONDS):
        end = int(np.searchsorted(t, float(second)))
        steps.append(("P", run.counts[k:end], dt[k:end]))
        d = run.gps.enu[second, :2] - run.gps.enu[second - 1, :2]
        steps.append(("G", float(vel[second, 0]), float(vel[second, 1]), float(d[0]), float(d[1])))
        k = end
    return steps


@pytest.mark.parametrize("board_name,arch", ARM)
def test_seed_kernel_on_arm_equals_cffi_bit_for_bit(board_name, arch, walk, natmods):
    from codegen.kernel.hostkernel import load_kernel

    board, run = walk
    steps = seed_steps(board, run)
    with qemu_arm.Session(firmware(board_name), board_name) as session:
        session.put_file("dr_native.mpy", natmods[arch])
        answers = windows.run(session, "dr_native", "seed", steps, 10)
    c = load_kernel().session()
    assert bool(answers[0].out[0]) == c.calibrate(steps[0][1])
    np.testing.assert_array_equal(answers[0].state[:4], c.q)
    cfg = ref.KernelConfig.from_board(board)
    case = Case(cfg, np.zeros(4), np.zeros(3), np.zeros(3), [s[1:] for s in steps[1:]], calib=steps[0][1])
    for (_, samples, dt), got, (r_d, r_v, _, bound_p, bound_v) in zip(steps[1:], answers[1:], run_reference(case)):
        d, v, _ = c.process(samples, dt)
        assert np.array_equal(got.out, np.concatenate([d, v])), (got.out, d, v)  # bit for bit, out
        assert np.array_equal(got.state[:4], c.q) and np.array_equal(got.state[4:7], c.v)  # and the state
        assert np.array_equal(got.state[7:10], c.gyro_bias_lsb)
        assert np.all(np.abs(got.out[:3] - r_d) <= bound_p) and np.all(np.abs(got.out[3:] - r_v) <= bound_v)
    assert np.linalg.norm(answers[-1].out[:3]) > 1.0  # the windows moved the device: not a run of zeros
    assert all(a.instructions > 100_000 for a in answers[1:])  # the clock counted the kernel's work


@pytest.mark.parametrize("board_name,arch", ARM)
def test_fused_on_arm_equals_cffi_bit_for_bit(board_name, arch, walk, natmods):
    from codegen.kernel.hostfused import load_fused

    _, run = walk
    steps = fused_steps(run)
    with qemu_arm.Session(firmware(board_name), board_name) as session:
        session.put_file("dr_native.mpy", natmods[arch])
        answers = windows.run(session, "dr_native", "fused", steps, F.STATE_LEN)
    c = load_fused().session()
    assert bool(answers[0].out[0]) == c.calibrate(steps[0][1])
    reference = F.FusedState()
    kcfg, fcfg = ref.KernelConfig.from_board(walk[0]), F.FusedConfig.from_board(walk[0])
    F.calibrate(reference, steps[0][1], kcfg)
    for item, got in zip(steps[1:], answers[1:]):
        if item[0] == "P":
            out = c.process(item[1], item[2])
            F.process(reference, item[1], item[2], kcfg, fcfg)
            assert np.array_equal(got.out, out), (item[0], got.out, out)
        else:
            c.position(*item[1:])
            c.gps(item[1], item[2])
            F.position_update(reference, *item[1:], fcfg)
            F.gps_update(reference, item[1], item[2], fcfg)
        want = c.state_vector()
        differ = np.flatnonzero(got.state.view(np.uint32) != want.view(np.uint32))
        assert differ.size == 0, [(F.STATE_FIELDS[i], got.state[i], want[i]) for i in differ[:5]]
    walked = np.hypot(*answers[-1].state[F.IDX["pe"]:F.IDX["pn"] + 1])
    expected = np.hypot(*reference.vector()[F.IDX["pe"]:F.IDX["pn"] + 1])
    assert walked > 5.0 and abs(walked - expected) < 0.01 * expected + 0.05  # float32 vs float64: centimetres
